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
    remove_stale_temporaries(dir, &name);
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    // create_new: never through a file or link someone planted under the name; take the next.
    let (tmp, file) = loop {
        let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tmp = dir.join(format!(".{name}.tmp-{}-{n}", std::process::id()));
        match fs::OpenOptions::new().write(true).create_new(true).open(&tmp) {
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists && n < 1_000_000 => continue,
            other => break (tmp.clone(), other.map_err(at(&tmp))?),
        }
    };
    let result = (|| {
        let mut f = file;
        f.write_all(bytes)?;
        f.sync_all()
    })();
    if let Err(e) = result {
        let _ = fs::remove_file(&tmp);
        return Err(at(&tmp)(e));
    }
    fs::rename(&tmp, path).map_err(at(path))?;
    // The rename is durable once the directory is.
    if let Ok(d) = fs::File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// Removes `.NAME.tmp-PID-N` files in `dir` left by processes that no longer run (a write
/// killed between create and rename).
fn remove_stale_temporaries(dir: &Path, name: &str) {
    let prefix = format!(".{name}.tmp-");
    let Ok(entries) = fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let file = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = file.strip_prefix(&prefix).and_then(|rest| rest.split('-').next()) else { continue };
        let alive = pid.parse::<u32>().is_ok_and(|p| p == std::process::id() || Path::new("/proc").join(pid).exists());
        if !alive && Path::new("/proc/self").exists() {
            let _ = fs::remove_file(entry.path());
        }
    }
}

/// Reads a whole file, naming it in the error.
pub fn read(path: &Path) -> Result<Vec<u8>, FileError> {
    fs::read(path).map_err(at(path))
}

/// Reads a whole UTF-8 file, naming it in the error.
pub fn read_to_string(path: &Path) -> Result<String, FileError> {
    fs::read_to_string(path).map_err(at(path))
}

/// What a file looks like from its first bytes, for errors that say which kind of file a
/// command got and, for the kinds this project reads, which command takes it: "a PNG image",
/// "a BVH motion capture (`flowmimic motion import` reads it)", ...
pub fn describe(path: &Path) -> String {
    if path.is_dir() {
        return "a directory".into();
    }
    let mut head = [0u8; 512];
    let n = match fs::File::open(path).and_then(|mut f| io::Read::read(&mut f, &mut head)) {
        Ok(n) => n,
        Err(e) => return format!("unreadable ({e})"),
    };
    let head = &head[..n];
    let text = std::str::from_utf8(head).map(str::trim_start);
    let kind = if head.starts_with(b"\x89PNG") {
        "a PNG image"
    } else if head.starts_with(b"GIF8") {
        "a GIF image"
    } else if head.starts_with(&[0xff, 0xd8]) {
        "a JPEG image"
    } else if head.len() > 8 && head[8] == b'{' {
        "a safetensors file"
    } else if text.is_ok_and(|t| t.starts_with("HIERARCHY")) {
        "a BVH motion capture (`flowmimic motion import` reads it)"
    } else if text.is_ok_and(|t| t.starts_with('{') && t.contains("\"Frames\"")) {
        "a DeepMimic motion (`flowmimic motion import` reads it)"
    } else if text.is_ok_and(|t| t.starts_with('{') || t.starts_with('[')) {
        "a JSON file"
    } else if n == 0 {
        "empty"
    } else if text.is_ok() || std::str::from_utf8(&head[..n.saturating_sub(3)]).is_ok() {
        "a text file"
    } else {
        "a binary file"
    };
    kind.into()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_are_described_by_their_first_bytes() {
        let dir = std::env::temp_dir().join(format!("flowmimic-io-describe-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let file = |name: &str, bytes: &[u8]| {
            let p = dir.join(name);
            fs::write(&p, bytes).unwrap();
            describe(&p)
        };
        assert_eq!(file("a.png", b"\x89PNG\r\n\x1a\n...."), "a PNG image");
        assert!(file("a.bvh", b"HIERARCHY\nROOT Hips\n").starts_with("a BVH motion capture"));
        assert!(file("a.txt", b"{\"Loop\": \"wrap\", \"Frames\": [[0.03]]}").starts_with("a DeepMimic motion"));
        assert_eq!(file("a.st", b"\x10\0\0\0\0\0\0\0{\"a\":1}"), "a safetensors file");
        assert_eq!(file("a.bin", &[0, 159, 146, 150, 1, 2, 3, 4, 0, 7]), "a binary file");
        assert_eq!(describe(&dir), "a directory");
        fs::remove_dir_all(&dir).unwrap();
    }

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
        // A temporary left by a killed writer (a PID that cannot run) is cleared by the next
        // write; a planted link never receives the bytes.
        let stale = path.with_file_name(".file.txt.tmp-4294967294-0");
        fs::write(&stale, b"half").unwrap();
        let victim = dir.join("victim");
        fs::write(&victim, b"safe").unwrap();
        for n in 0..64 {
            let planted = path.with_file_name(format!(".file.txt.tmp-{}-{n}", std::process::id()));
            let _ = std::os::unix::fs::symlink(&victim, planted);
        }
        write_atomic(&path, b"three").unwrap();
        write_atomic(&path, b"four").unwrap();
        assert!(!stale.exists(), "stale temporary kept");
        assert_eq!(read(&victim).unwrap(), b"safe");
        assert_eq!(read(&path).unwrap(), b"four");
        assert_eq!(fs::read_dir(&dir).unwrap().count(), 2, "sub/ and victim");
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

/// safetensors files of `f32` tensors with string metadata: the format of every weight,
/// checkpoint and statistics file, readable with `safetensors.numpy.load_file` in Python.
pub mod tensors {
    use super::{FileError, le};
    use safetensors::{Dtype, SafeTensors, tensor::TensorView};
    use std::collections::HashMap;
    use std::path::{Path, PathBuf};

    /// A file that is missing, unreadable, or not what it should be.
    #[derive(Debug)]
    pub struct TensorError {
        pub path: PathBuf,
        pub message: String,
    }

    impl std::fmt::Display for TensorError {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "{}: {}", self.path.display(), self.message)
        }
    }

    impl std::error::Error for TensorError {}

    impl From<FileError> for TensorError {
        fn from(e: FileError) -> Self {
            Self { message: e.source.to_string(), path: e.path }
        }
    }

    /// Writes `(name, shape, values)` tensors and metadata to `path` atomically.
    pub fn save(
        path: &Path,
        tensors: &[(&str, Vec<usize>, &[f32])],
        meta: HashMap<String, String>,
    ) -> Result<(), TensorError> {
        let bytes: Vec<Vec<u8>> = tensors.iter().map(|(_, _, v)| le::bytes(v.iter().copied())).collect();
        let views = tensors
            .iter()
            .zip(&bytes)
            .map(|((name, shape, _), b)| {
                let view = TensorView::new(Dtype::F32, shape.clone(), b)
                    .map_err(|e| TensorError { path: path.into(), message: format!("tensor '{name}': {e}") })?;
                Ok((*name, view))
            })
            .collect::<Result<Vec<_>, TensorError>>()?;
        let out = safetensors::serialize(views, Some(meta))
            .map_err(|e| TensorError { path: path.into(), message: e.to_string() })?;
        Ok(super::write_atomic(path, &out)?)
    }

    /// A safetensors file read into memory.
    pub struct TensorFile {
        pub path: PathBuf,
        bytes: Vec<u8>,
        meta: HashMap<String, String>,
    }

    impl TensorFile {
        pub fn open(path: &Path) -> Result<Self, TensorError> {
            let bytes = super::read(path)?;
            let bad = |e: safetensors::SafeTensorError| TensorError {
                path: path.into(),
                message: format!("not a readable safetensors file ({e}): it is {}", super::describe(path)),
            };
            let (_, header) = SafeTensors::read_metadata(&bytes).map_err(bad)?;
            let meta = header.metadata().clone().unwrap_or_default();
            SafeTensors::deserialize(&bytes).map_err(bad)?;
            Ok(Self { path: path.into(), bytes, meta })
        }

        pub fn error(&self, message: impl Into<String>) -> TensorError {
            TensorError { path: self.path.clone(), message: message.into() }
        }

        /// A metadata entry.
        pub fn meta(&self, key: &str) -> Result<&str, TensorError> {
            self.meta.get(key).map(String::as_str).ok_or_else(|| self.error(format!("metadata '{key}' is missing")))
        }

        /// The shape of tensor `name`.
        pub fn shape(&self, name: &str) -> Result<Vec<usize>, TensorError> {
            let st = SafeTensors::deserialize(&self.bytes).map_err(|e| self.error(e.to_string()))?;
            let t = st.tensor(name).map_err(|_| self.error(format!("tensor '{name}' is missing")))?;
            Ok(t.shape().to_vec())
        }

        /// The tensor `name`, which must be `f32` of exactly `shape`.
        pub fn f32(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, TensorError> {
            let st = SafeTensors::deserialize(&self.bytes).map_err(|e| self.error(e.to_string()))?;
            let t = st.tensor(name).map_err(|_| self.error(format!("tensor '{name}' is missing")))?;
            if t.dtype() != Dtype::F32 || t.shape() != shape {
                return Err(self.error(format!(
                    "tensor '{name}' is {:?} {:?}, expected F32 {shape:?}",
                    t.dtype(),
                    t.shape()
                )));
            }
            Ok(le::values(t.data()))
        }
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn round_trip_and_clear_errors() {
            let dir = std::env::temp_dir().join(format!("flowmimic-tensors-{}", std::process::id()));
            let path = dir.join("t.safetensors");
            let meta = HashMap::from([("k".to_string(), "v".to_string())]);
            save(&path, &[("a", vec![2, 2], &[1.0, 2.0, 3.0, 4.0])], meta).unwrap();
            let f = TensorFile::open(&path).unwrap();
            assert_eq!(f.f32("a", &[2, 2]).unwrap(), vec![1.0, 2.0, 3.0, 4.0]);
            assert_eq!(f.meta("k").unwrap(), "v");
            let err = f.f32("a", &[4]).unwrap_err().to_string();
            assert!(err.contains("t.safetensors") && err.contains("expected F32 [4]"), "{err}");
            assert!(f.f32("b", &[1]).unwrap_err().to_string().contains("'b' is missing"));
            std::fs::write(&path, b"garbage").unwrap();
            let err = TensorFile::open(&path).err().unwrap().to_string();
            assert!(err.contains("not a readable safetensors"), "{err}");
            std::fs::remove_dir_all(&dir).unwrap();
        }
    }
}
