//! Dataset shards, read through a manifest that lists them with their true checksum (so the
//! fuzzer reaches the tensor checks, not only the checksum's).
#![no_main]
use libfuzzer_sys::fuzz_target;
use sha2::{Digest, Sha256};

fuzz_target!(|data: &[u8]| {
    let dir = flowmimic_fuzz::scratch().join("shard");
    std::fs::create_dir_all(&dir).expect("dataset directory");
    let mut manifest: serde_json::Value =
        serde_json::from_slice(flowmimic_fuzz::seed("manifest/manifest.json")).expect("seed manifest");
    let shard = &mut manifest["shards"][0];
    let file = shard["file"].as_str().expect("shard file").to_string();
    shard["sha256"] = Sha256::digest(data).iter().map(|b| format!("{b:02x}")).collect::<String>().into();
    std::fs::write(dir.join(&file), data).expect("shard");
    std::fs::write(dir.join("manifest.json"), manifest.to_string()).expect("manifest");
    if let Ok(dataset) = flowmimic_data::Dataset::open(&dir) {
        let _ = dataset.load_all();
    }
});
