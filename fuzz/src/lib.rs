//! What the fuzz targets share. Each target writes its input where a user's file would be and
//! calls the loader the `flowmimic` command calls on it, so that the code fuzzed is the code run.

use flowmimic_sim::{Humanoid, SimConfig};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

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

/// A valid file made by `scripts/fuzz-seeds.sh` (from `fuzz/fixtures/`), for the parts of a
/// directory that a target holds fixed while it fuzzes another.
pub fn fixture(name: &str) -> Vec<u8> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures").join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}; run scripts/fuzz-seeds.sh", path.display()))
}

/// The simulated humanoid of the default settings, built once.
pub fn humanoid() -> &'static Arc<Humanoid> {
    static HUMANOID: OnceLock<Arc<Humanoid>> = OnceLock::new();
    HUMANOID.get_or_init(|| Humanoid::new(SimConfig::default()).expect("build the humanoid"))
}
