//! Clip files (`*.clip.safetensors`), as every command that takes `--clip` reads them.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = flowmimic_fuzz::write("input.clip.safetensors", data);
    let _ = flowmimic_motion::Clip::load(flowmimic_fuzz::humanoid(), &path);
});
