//! Rollouts (`*.rollout.safetensors`), as `eval`, `render` and `view` read them.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = flowmimic_fuzz::write("input.rollout.safetensors", data);
    let _ = flowmimic_control::Rollout::load(&path);
});
