//! File helpers shared by every stage.
//!
//! Artifacts are written atomically: to a temporary file in the same directory, flushed to
//! disk, then renamed over the target. A crash or kill mid-write leaves the old file (or none),
//! never a truncated one.

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// An I/O failure with the file it concerns.
#[derive(Debug)]
pub struct FileError {
    pub path: PathBuf,
    pub source: io::Error,
}

impl std::fmt::Display for FileError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.path.display(), self.source)
    }
}

// The message already carries the cause, so it is not also reported as `source()` (error
// chains would print it twice).
impl std::error::Error for FileError {}

fn at(path: &Path) -> impl FnOnce(io::Error) -> FileError + '_ {
    move |source| FileError { path: path.to_path_buf(), source }
}

/// Writes `bytes` to `path` atomically, creating parent directories.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FileError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    fs::create_dir_all(dir).map_err(at(dir))?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    let result = (|| {
        let mut f = fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()
    })();
    if let Err(e) = result {
        let _ = fs::remove_file(&tmp);
        return Err(at(&tmp)(e));
    }
    fs::rename(&tmp, path).map_err(at(path))
}

/// Reads a whole file, naming it in the error.
pub fn read(path: &Path) -> Result<Vec<u8>, FileError> {
    fs::read(path).map_err(at(path))
}

/// Reads a whole UTF-8 file, naming it in the error.
pub fn read_to_string(path: &Path) -> Result<String, FileError> {
    fs::read_to_string(path).map_err(at(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_content_and_leaves_no_temporaries() {
        let dir = std::env::temp_dir().join(format!("flowmimic-io-{}", std::process::id()));
        let path = dir.join("sub/file.txt");
        write_atomic(&path, b"one").unwrap();
        write_atomic(&path, b"two").unwrap();
        assert_eq!(read(&path).unwrap(), b"two");
        let entries: Vec<_> = fs::read_dir(path.parent().unwrap()).unwrap().collect();
        assert_eq!(entries.len(), 1, "no temporary files left behind");
        let err = read(&dir.join("missing")).unwrap_err().to_string();
        assert!(err.contains("missing"), "{err}");
        fs::remove_dir_all(&dir).unwrap();
    }
}

/// Little-endian byte layouts of numeric slices, as safetensors stores tensors.
pub mod le {
    /// Implemented for the element types our files store.
    pub trait Scalar: Copy {
        const SIZE: usize;
        fn write(self, out: &mut Vec<u8>);
        fn read(bytes: &[u8]) -> Self;
    }

    macro_rules! scalar {
        ($($t:ty),*) => {$(
            impl Scalar for $t {
                const SIZE: usize = std::mem::size_of::<$t>();
                fn write(self, out: &mut Vec<u8>) {
                    out.extend_from_slice(&self.to_le_bytes());
                }
                fn read(bytes: &[u8]) -> Self {
                    <$t>::from_le_bytes(bytes.try_into().expect("chunk of the scalar's size"))
                }
            }
        )*};
    }
    scalar!(f32, f64, u32);

    /// The bytes of `values`.
    pub fn bytes<T: Scalar>(values: impl IntoIterator<Item = T>) -> Vec<u8> {
        let mut out = Vec::new();
        values.into_iter().for_each(|v| v.write(&mut out));
        out
    }

    /// The values in `bytes` (a trailing partial value is ignored).
    pub fn values<T: Scalar>(bytes: &[u8]) -> Vec<T> {
        bytes.chunks_exact(T::SIZE).map(T::read).collect()
    }

    #[cfg(test)]
    mod tests {
        #[test]
        fn round_trips() {
            let xs = [1.5f32, -2.0, f32::MAX];
            assert_eq!(super::values::<f32>(&super::bytes(xs)), xs);
            let ys = [0.1f64, 1e300];
            assert_eq!(super::values::<f64>(&super::bytes(ys)), ys);
            assert_eq!(super::bytes([1u32]), vec![1, 0, 0, 0]);
        }
    }
}
