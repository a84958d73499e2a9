//! What the binary's integration tests share: running `flowmimic` on the tiny preset.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// `flowmimic --preset tiny ARGS` in `dir`: (succeeded, stdout and stderr).
pub fn flowmimic(dir: &Path, args: &[&str]) -> (bool, String) {
    let out = command(dir, args).output().expect("the binary runs");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    (out.status.success(), text)
}

/// The command line of `flowmimic --preset tiny ARGS` in `dir`, to run or spawn.
pub fn command(dir: &Path, args: &[&str]) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_flowmimic"));
    command.current_dir(dir).args(["--preset", "tiny"]).args(args);
    command
}

pub fn ok(dir: &Path, args: &[&str]) -> String {
    let (success, text) = flowmimic(dir, args);
    assert!(success, "flowmimic {args:?} failed:\n{text}");
    text
}

pub fn workdir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("flowmimic-cli-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A safetensors file's tensor bytes (after the header, whose metadata order may vary).
pub fn tensor_bytes(path: &Path) -> Vec<u8> {
    let b = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let header = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
    b[8 + header..].to_vec()
}
