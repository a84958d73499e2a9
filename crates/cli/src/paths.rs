//! Where the shipped files are, and which model a command drives when none is named.

use std::path::{Path, PathBuf};

/// The shipped default guidance model, relative to the checkout.
pub const SHIPPED_MODEL: &str = "pretrained/models/fm";
/// The captures the corpus reads, beside the checkout.
pub const MOCAP: &str = "../shared/data/mocap";
/// The Flow Matching model `make run` (`flowmimic pipeline`) trains.
pub const PIPELINE_MODEL: &str = "runs/pipeline/model/fm";

/// A shipped file or directory (`pretrained/...`): from the current directory when it is the
/// checkout, else from the checkout that holds this binary (`target/release/flowmimic`), else
/// from the one it was built in; the relative path itself when none has it.
pub fn shipped(relative: &str) -> PathBuf {
    let exe = std::env::current_exe().ok();
    let roots = std::iter::once(PathBuf::from("."))
        .chain(exe.iter().flat_map(|e| e.ancestors().skip(1).map(Path::to_path_buf)))
        .chain(std::iter::once(PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))));
    roots.map(|root| root.join(relative)).find(|p| p.exists()).unwrap_or_else(|| PathBuf::from(relative))
}

/// A path as given, or where it is missing and relative, the same path from the checkout (so
/// that `pretrained/models/fm` and `../shared/data/mocap` work from any folder).
pub fn resolve(path: &Path) -> PathBuf {
    if path.exists() || path.is_absolute() {
        return path.to_path_buf();
    }
    shipped(&path.to_string_lossy())
}

/// The model a command drives: `--model`, else the one `make run` trained when it exists in
/// the current directory, else the shipped default; says which when none was named.
pub fn model_or_default(model: Option<PathBuf>) -> PathBuf {
    if let Some(m) = model {
        return resolve(&m);
    }
    if Path::new(PIPELINE_MODEL).join("model.safetensors").exists() {
        eprintln!("model: {PIPELINE_MODEL}, the one `make run` trained (--model {SHIPPED_MODEL} for the shipped one)");
        return PathBuf::from(PIPELINE_MODEL);
    }
    let shipped = shipped(SHIPPED_MODEL);
    eprintln!("model: {}, the shipped default (--model DIR for another)", shipped.display());
    shipped
}
