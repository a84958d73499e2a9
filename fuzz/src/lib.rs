//! What the fuzz targets share. Each target writes its input where a user's file would be and
//! calls the loader the `flowmimic` command calls on it, so that the code fuzzed is the code run.

use flowmimic_sim::{Humanoid, SimConfig};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

/// A directory of this process's own under the system's temporary directory.
pub fn scratch() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("flowmimic-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("create the scratch directory");
        dir
    })
}

/// Writes `bytes` to the scratch file `name` and returns its path.
pub fn write(name: &str, bytes: &[u8]) -> PathBuf {
    let path = scratch().join(name);
    std::fs::write(&path, bytes).expect("write the fuzz input");
    path
}

/// A committed seed (`fuzz/corpus/TARGET/FILE`, made by `scripts/fuzz-seeds.sh`), for the
/// files of a directory that a target holds fixed while it fuzzes another; read once.
pub fn seed(name: &'static str) -> &'static [u8] {
    static SEEDS: Mutex<BTreeMap<&str, &[u8]>> = Mutex::new(BTreeMap::new());
    let mut seeds = SEEDS.lock().expect("seed cache");
    seeds.entry(name).or_insert_with(|| {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("corpus").join(name);
        let bytes =
            std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}; run scripts/fuzz-seeds.sh", path.display()));
        Vec::leak(bytes)
    })
}

/// The simulated humanoid of the default settings, built once.
pub fn humanoid() -> &'static Arc<Humanoid> {
    static HUMANOID: OnceLock<Arc<Humanoid>> = OnceLock::new();
    HUMANOID.get_or_init(|| Humanoid::new(SimConfig::default()).expect("build the humanoid"))
}
