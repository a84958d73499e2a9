//! The `flowmimic` binary end to end on the `tiny` preset: the stages hand files to each other
//! exactly as a user's commands do.

use std::path::{Path, PathBuf};
use std::process::Command;

fn flowmimic(dir: &Path, args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_flowmimic"))
        .current_dir(dir)
        .args(["--preset", "tiny"])
        .args(args)
        .output()
        .expect("the binary runs");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    (out.status.success(), text)
}

fn ok(dir: &Path, args: &[&str]) -> String {
    let (success, text) = flowmimic(dir, args);
    assert!(success, "flowmimic {args:?} failed:\n{text}");
    text
}

fn workdir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("flowmimic-cli-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn stages_connect_through_their_files() {
    let dir = workdir("stages");
    let table = ok(&dir, &["motion", "generate", "--duration", "1.5", "--name", "w", "-o", "clips"]);
    assert!(table.contains("w ") && dir.join("clips/w.clip.safetensors").exists(), "{table}");
    let train = ok(&dir, &["track", "train", "--clip", "clips/w.clip.safetensors", "-o", "run", "--iterations", "2"]);
    assert!(train.contains("[    2/2]"), "{train}");
    for file in ["policy.safetensors", "clip.safetensors", "log.csv", "config.json", "reward.png", "body_error.svg"] {
        assert!(dir.join("run").join(file).exists(), "run/{file} missing");
    }
    // Training again into the same run without --resume is refused; with it, it continues.
    let (success, text) = flowmimic(&dir, &["track", "train", "--clip", "clips/w.clip.safetensors", "-o", "run"]);
    assert!(!success && text.contains("--resume"), "{text}");
    let resumed = ok(
        &dir,
        &["track", "train", "--clip", "clips/w.clip.safetensors", "-o", "run", "--resume", "--iterations", "3"],
    );
    assert!(resumed.contains("resumed") && resumed.contains("[    3/3]"), "{resumed}");
    let eval = ok(&dir, &["track", "eval", "run", "--episodes", "2"]);
    assert!(eval.contains("\"success_rate\"") && eval.contains("\"clip_steps\": 45"), "{eval}");
    let collect = ok(&dir, &["collect", "run", "-o", "data"]);
    assert!(collect.contains("steps/s") && collect.contains("fall rate"), "{collect}");
    let inspect = ok(&dir, &["dataset", "inspect", "data"]);
    assert!(inspect.contains("feature ranges") && dir.join("data/coverage_root_speed.png").exists(), "{inspect}");
    let stats = ok(&dir, &["dataset", "stats", "data", "--history", "2", "--horizon", "3"]);
    assert!(stats.contains("windows") && dir.join("data/stats-N2-H3.safetensors").exists(), "{stats}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_input_is_a_clear_error_not_a_crash() {
    let dir = workdir("bad-input");
    std::fs::write(dir.join("bad.bvh"), "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0\n").unwrap();
    let (success, text) = flowmimic(&dir, &["motion", "import", "bad.bvh"]);
    assert!(!success && text.contains("bad.bvh") && text.contains("line"), "{text}");
    std::fs::write(dir.join("typo.toml"), "[track]\nenvz = 3\n").unwrap();
    let (success, text) = flowmimic(&dir, &["--config", "typo.toml", "config"]);
    assert!(!success && text.contains("envz"), "{text}");
    let (success, text) = flowmimic(&dir, &["track", "eval", "no-such-run"]);
    assert!(!success && text.contains("no-such-run"), "{text}");
    assert_eq!(text.matches("No such file").count(), 1, "the cause is said once: {text}");
    std::fs::remove_dir_all(&dir).ok();
}
