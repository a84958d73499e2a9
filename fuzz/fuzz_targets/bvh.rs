//! `flowmimic motion import FILE.bvh`: parsing, joint mapping and retargeting.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = flowmimic_fuzz::write("input.bvh", data);
    let _ = flowmimic_motion::import(flowmimic_fuzz::humanoid(), &path, &Default::default());
});
