//! Trajectory models (`model.safetensors` beside a valid `stats.safetensors`), as `run`,
//! `eval` and `demo` load them.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let dir = flowmimic_fuzz::scratch().join("model");
    std::fs::create_dir_all(&dir).expect("model directory");
    std::fs::write(dir.join("stats.safetensors"), flowmimic_fuzz::seed("stats/stats.safetensors")).expect("stats");
    std::fs::write(dir.join("model.safetensors"), data).expect("model");
    let _ = flowmimic_model::TrajectoryModel::load(&dir);
});
