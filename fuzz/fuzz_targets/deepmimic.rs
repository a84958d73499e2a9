//! `flowmimic motion import FILE.txt`: DeepMimic clips, parsed and retargeted.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = flowmimic_fuzz::write("input.txt", data);
    let _ = flowmimic_motion::import(flowmimic_fuzz::humanoid(), &path, &Default::default());
});
