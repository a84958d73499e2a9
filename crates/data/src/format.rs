//! The dataset on disk: a directory with `manifest.json` and one safetensors shard per clip.
//!
//! Each shard `<clip>.rollouts.safetensors` holds one row per control step, rollouts one after
//! another (readable in Python with `safetensors.numpy.load_file`, memory-mappable with
//! `safe_open`):
//!
//! | tensor          | dtype | shape      | what                                                        |
//! |-----------------|-------|------------|-------------------------------------------------------------|
//! | `state`         | F32   | `[S, 165]` | the state in its own character frame (flowmimic_sim::state)  |
//! | `action`        | F32   | `[S, 69]`  | the expert's clean action for that (noisy) state             |
//! | `noisy_action`  | F32   | `[S, 69]`  | the action executed (the expert's with N(0, sigma^2) on its output) |
//! | `root_pose`     | F32   | `[S, 3]`   | root x, y (m) and heading (rad) in the world, to re-express states in another step's frame |
//! | `done`          | U8    | `[S]`      | 1 on the last step of an episode (fall or rollout end)       |
//! | `sigma`         | F32   | `[S]`      | action-noise scale of the rollout                            |
//! | `rollout`       | U32   | `[S]`      | rollout index within the shard                               |
//! | `frame`         | U32   | `[S]`      | reference frame the expert was tracking                      |
//!
//! `manifest.json` lists the dimensions, feature and body names, the control rate and every
//! shard with its clip, expert, seed, step count and SHA-256 (and `mirror_of`, the source's
//! SHA-256, for a shard that is another's left-right mirror image). Adding a clip writes one
//! shard and rewrites only the manifest (atomically).

use crate::DataError;
use flowmimic_io::le;
use flowmimic_sim::Mirror;
use flowmimic_sim::skeleton::{BODY_NAMES, hinge_names};
use flowmimic_sim::state::state_feature_names;
use flowmimic_sim::{CONTROL_HZ, NUM_DOFS, STATE_DIM};
use safetensors::{Dtype, SafeTensors, tensor::TensorView};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};

pub const FORMAT: &str = "flowmimic-rollouts/1";
pub const MANIFEST: &str = "manifest.json";

/// One shard's entry in the manifest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShardInfo {
    pub file: String,
    pub clip: String,
    pub expert: String,
    pub seed: u64,
    pub steps: usize,
    pub rollouts: usize,
    /// (sigma, environments) allocation.
    pub sigmas: Vec<(f32, usize)>,
    /// (sigma, episodes, falls) of the collection.
    pub falls: Vec<(f32, usize, usize)>,
    pub sha256: String,
    /// For a mirror image ([`Dataset::add_mirror_images`]), the SHA-256 of the shard it mirrors;
    /// `None` for collected rollouts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mirror_of: Option<String>,
}

/// `manifest.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub state_dim: usize,
    pub action_dim: usize,
    pub control_hz: f64,
    pub state_features: Vec<String>,
    pub action_features: Vec<String>,
    pub body_names: Vec<String>,
    pub shards: Vec<ShardInfo>,
}

impl Default for Manifest {
    fn default() -> Self {
        Self {
            format: FORMAT.into(),
            state_dim: STATE_DIM,
            action_dim: NUM_DOFS,
            control_hz: CONTROL_HZ,
            state_features: state_feature_names(),
            action_features: hinge_names(),
            body_names: BODY_NAMES.iter().map(|s| s.to_string()).collect(),
            shards: Vec::new(),
        }
    }
}

/// The steps of one shard, in memory.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Shard {
    pub state: Vec<f32>,
    pub action: Vec<f32>,
    pub noisy_action: Vec<f32>,
    pub root_pose: Vec<f32>,
    pub done: Vec<u8>,
    pub sigma: Vec<f32>,
    pub rollout: Vec<u32>,
    pub frame: Vec<u32>,
}

impl Shard {
    pub fn steps(&self) -> usize {
        self.done.len()
    }

    /// Keeps the first `steps` steps.
    pub fn truncate(&mut self, steps: usize) {
        self.state.truncate(steps * STATE_DIM);
        self.action.truncate(steps * NUM_DOFS);
        self.noisy_action.truncate(steps * NUM_DOFS);
        self.root_pose.truncate(steps * 3);
        self.done.truncate(steps);
        self.sigma.truncate(steps);
        self.rollout.truncate(steps);
        self.frame.truncate(steps);
    }

    /// Appends another buffer's steps.
    pub fn extend_lane(&mut self, other: Shard) {
        self.state.extend(other.state);
        self.action.extend(other.action);
        self.noisy_action.extend(other.noisy_action);
        self.root_pose.extend(other.root_pose);
        self.done.extend(other.done);
        self.sigma.extend(other.sigma);
        self.rollout.extend(other.rollout);
        self.frame.extend(other.frame);
    }

    /// The mirror image of every step ([`Mirror`]): states and actions mirrored left to right,
    /// the world pose's y and heading negated.
    pub fn mirror_image(&self) -> Shard {
        let mut image = self.clone();
        Mirror::state().apply_rows(&mut image.state);
        let actions = Mirror::action();
        actions.apply_rows(&mut image.action);
        actions.apply_rows(&mut image.noisy_action);
        for pose in image.root_pose.chunks_mut(3) {
            pose[1] = -pose[1];
            pose[2] = -pose[2];
        }
        image
    }

    fn bytes(&self) -> Result<Vec<u8>, DataError> {
        let (le32, leu) = (|v: &[f32]| le::bytes(v.iter().copied()), |v: &[u32]| le::bytes(v.iter().copied()));
        let s = self.steps();
        let tensors: Vec<(&str, Dtype, Vec<usize>, Vec<u8>)> = vec![
            ("state", Dtype::F32, vec![s, STATE_DIM], le32(&self.state)),
            ("action", Dtype::F32, vec![s, NUM_DOFS], le32(&self.action)),
            ("noisy_action", Dtype::F32, vec![s, NUM_DOFS], le32(&self.noisy_action)),
            ("root_pose", Dtype::F32, vec![s, 3], le32(&self.root_pose)),
            ("done", Dtype::U8, vec![s], self.done.clone()),
            ("sigma", Dtype::F32, vec![s], le32(&self.sigma)),
            ("rollout", Dtype::U32, vec![s], leu(&self.rollout)),
            ("frame", Dtype::U32, vec![s], leu(&self.frame)),
        ];
        let views: Vec<(&str, TensorView)> = tensors
            .iter()
            .map(|(n, d, shape, b)| TensorView::new(*d, shape.clone(), b).map(|v| (*n, v)))
            .collect::<Result<_, _>>()
            .map_err(|e| DataError::Invalid(format!("shard tensors have inconsistent sizes: {e}")))?;
        safetensors::serialize(views, Some([("format".to_string(), FORMAT.to_string())].into()))
            .map_err(|e| DataError::Invalid(e.to_string()))
    }

    fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self, DataError> {
        let bad = |m: String| DataError::Shard { path: path.into(), message: m };
        let st = SafeTensors::deserialize(bytes).map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let get = |name: &str, dtype: Dtype, width: usize| -> Result<(Vec<u8>, usize), DataError> {
            let t = st.tensor(name).map_err(|e| bad(format!("tensor '{name}': {e}")))?;
            let shape = t.shape();
            let ok = t.dtype() == dtype
                && match width {
                    0 => shape.len() == 1,
                    w => shape.len() == 2 && shape[1] == w,
                };
            if !ok {
                return Err(bad(format!(
                    "tensor '{name}' is {:?} {:?}; expected {dtype:?} with width {width}",
                    t.dtype(),
                    shape
                )));
            }
            Ok((t.data().to_vec(), shape[0]))
        };
        let f32s = |b: Vec<u8>| le::values::<f32>(&b);
        let u32s = |b: Vec<u8>| le::values::<u32>(&b);
        let (state, s) = get("state", Dtype::F32, STATE_DIM)?;
        let shard = Shard {
            state: f32s(state),
            action: f32s(get("action", Dtype::F32, NUM_DOFS)?.0),
            noisy_action: f32s(get("noisy_action", Dtype::F32, NUM_DOFS)?.0),
            root_pose: f32s(get("root_pose", Dtype::F32, 3)?.0),
            done: get("done", Dtype::U8, 0)?.0,
            sigma: f32s(get("sigma", Dtype::F32, 0)?.0),
            rollout: u32s(get("rollout", Dtype::U32, 0)?.0),
            frame: u32s(get("frame", Dtype::U32, 0)?.0),
        };
        if [
            shard.done.len(),
            shard.sigma.len(),
            shard.rollout.len(),
            shard.frame.len(),
            shard.root_pose.len() / 3,
            shard.action.len() / NUM_DOFS,
        ]
        .iter()
        .any(|&n| n != s)
        {
            return Err(bad("tensors disagree on the number of steps".into()));
        }
        if shard.state.iter().chain(&shard.action).any(|x| !x.is_finite()) {
            return Err(bad("non-finite state or action values".into()));
        }
        Ok(shard)
    }
}

fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// A dataset directory.
pub struct Dataset {
    pub dir: PathBuf,
    pub manifest: Manifest,
}

impl Dataset {
    /// The shards' checksums, joined: what statistics and models trained on it record.
    pub fn shards_key(&self) -> String {
        self.manifest.shards.iter().map(|s| s.sha256.as_str()).collect::<Vec<_>>().join(",")
    }

    /// Opens `dir`, or starts an empty dataset there if it has no manifest yet.
    pub fn open_or_create(dir: &Path) -> Result<Self, DataError> {
        let path = dir.join(MANIFEST);
        if path.exists() { Self::open(dir) } else { Ok(Self { dir: dir.into(), manifest: Manifest::default() }) }
    }

    /// Opens an existing dataset and checks its manifest against this build's dimensions.
    pub fn open(dir: &Path) -> Result<Self, DataError> {
        let path = dir.join(MANIFEST);
        let text = flowmimic_io::read_to_string(&path)?;
        let manifest: Manifest = serde_json::from_str(&text)
            .map_err(|e| DataError::Shard { path: path.clone(), message: format!("invalid manifest: {e}") })?;
        let expected = Manifest::default();
        if manifest.format != FORMAT
            || manifest.state_dim != STATE_DIM
            || manifest.action_dim != NUM_DOFS
            || manifest.state_features != expected.state_features
        {
            return Err(DataError::Shard {
                path,
                message: format!(
                    "dataset is {} with state {} and action {}; this build reads {FORMAT} with state {STATE_DIM} and action {NUM_DOFS}",
                    manifest.format, manifest.state_dim, manifest.action_dim
                ),
            });
        }
        Ok(Self { dir: dir.into(), manifest })
    }

    /// Writes a clip's shard and records it (replacing an earlier shard of the same clip).
    pub fn add(&mut self, mut info: ShardInfo, shard: &Shard) -> Result<(), DataError> {
        let bytes = shard.bytes()?;
        info.sha256 = sha256_hex(&bytes);
        info.steps = shard.steps();
        flowmimic_io::write_atomic(&self.dir.join(&info.file), &bytes)?;
        self.manifest.shards.retain(|s| s.clip != info.clip);
        self.manifest.shards.push(info);
        let json = serde_json::to_string_pretty(&self.manifest).expect("json");
        flowmimic_io::write_atomic(&self.dir.join(MANIFEST), json.as_bytes())?;
        Ok(())
    }

    /// Adds the mirror image ([`Shard::mirror_image`]) of every collected shard that has none
    /// yet, as the clip `<clip>-mirrored`, and returns the clips added. The collected shards
    /// stay as they are; a second call adds nothing, and a clip collected again since is
    /// mirrored again.
    pub fn add_mirror_images(&mut self) -> Result<Vec<String>, DataError> {
        let shards = &self.manifest.shards;
        let missing: Vec<ShardInfo> = shards
            .iter()
            .filter(|s| s.mirror_of.is_none() && !shards.iter().any(|m| m.mirror_of.as_ref() == Some(&s.sha256)))
            .cloned()
            .collect();
        let mut added = Vec::new();
        for info in missing {
            let image = self.load(&info)?.mirror_image();
            let clip = format!("{}-mirrored", info.clip);
            let (file, mirror_of) = (format!("{clip}.rollouts.safetensors"), Some(info.sha256.clone()));
            self.add(ShardInfo { clip: clip.clone(), file, mirror_of, ..info }, &image)?;
            added.push(clip);
        }
        Ok(added)
    }

    /// Reads a shard, verifying its checksum and dimensions.
    pub fn load(&self, info: &ShardInfo) -> Result<Shard, DataError> {
        let path = self.dir.join(&info.file);
        let bytes = flowmimic_io::read(&path)?;
        let sum = sha256_hex(&bytes);
        if sum != info.sha256 {
            return Err(DataError::Shard {
                path,
                message: format!("checksum {sum} does not match the manifest's {}", info.sha256),
            });
        }
        let shard = Shard::from_bytes(&bytes, &path)?;
        if shard.steps() != info.steps {
            return Err(DataError::Shard {
                path,
                message: format!("{} steps; the manifest says {}", shard.steps(), info.steps),
            });
        }
        Ok(shard)
    }

    /// All shards, concatenated in manifest order.
    pub fn load_all(&self) -> Result<Vec<(ShardInfo, Shard)>, DataError> {
        self.manifest.shards.iter().map(|i| Ok((i.clone(), self.load(i)?))).collect()
    }
}
