//! Expert checkpoints (`policy.safetensors`), as `track eval` and `collect` read them.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = flowmimic_fuzz::write("policy.safetensors", data);
    if let Ok(checkpoint) = flowmimic_track::train::Checkpoint::read(&path) {
        let _ = checkpoint.policy();
    }
});
