//! `--config FILE.toml` on top of a preset: the `flowmimic` command's own config module.
#![no_main]
use libfuzzer_sys::fuzz_target;

#[allow(dead_code)]
#[path = "../../crates/cli/src/config.rs"]
mod config;

fuzz_target!(|data: &[u8]| {
    let path = flowmimic_fuzz::write("input.toml", data);
    let _ = config::Config::load("tiny", Some(&path));
});
