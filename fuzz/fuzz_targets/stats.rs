//! Window statistics (`stats.safetensors`), as `train` and model loading read them.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = flowmimic_fuzz::write("stats.safetensors", data);
    let _ = flowmimic_data::Stats::load(&path);
});
