//! Dataset manifests (`manifest.json`) beside a valid shard.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let dir = flowmimic_fuzz::scratch().join("manifest");
    std::fs::create_dir_all(&dir).expect("dataset directory");
    let manifest: serde_json::Value =
        serde_json::from_slice(flowmimic_fuzz::seed("manifest/manifest.json")).expect("seed manifest");
    let file = manifest["shards"][0]["file"].as_str().expect("shard file");
    std::fs::write(dir.join(file), flowmimic_fuzz::seed("shard/walk.rollouts.safetensors")).expect("shard");
    std::fs::write(dir.join("manifest.json"), data).expect("manifest");
    if let Ok(dataset) = flowmimic_data::Dataset::open(&dir) {
        let _ = dataset.load_all();
    }
});
