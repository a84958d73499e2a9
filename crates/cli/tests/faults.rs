//! Faults: `train` and `track train` killed with SIGKILL at random moments and resumed, and the
//! trajectory model trained on 1 and on 2 threads.

mod common;

use common::{command, ok, tensor_bytes, workdir};
use rand::{Rng, SeedableRng};
use std::path::Path;
use std::time::Duration;

/// A clip, a 2-iteration expert and its tiny dataset in `dir`.
fn tiny_dataset(dir: &Path) {
    ok(dir, &["motion", "generate", "--duration", "1.5", "--name", "w", "-o", "clips"]);
    ok(dir, &["track", "train", "--clip", "clips/w.clip.safetensors", "-o", "expert", "--iterations", "2"]);
    ok(dir, &["collect", "expert", "-o", "data"]);
}

/// Every file shown under its final name is whole (temporaries are dot-files): safetensors
/// header and data agree with the file's length, CSV rows all have the header's columns and
/// the text ends with a newline, JSON parses.
fn assert_whole(dir: &Path, when: &str) {
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let (path, name) = (entry.path(), entry.file_name().to_string_lossy().into_owned());
        if name.starts_with('.') {
            continue;
        }
        let bytes = std::fs::read(&path).unwrap();
        let what = format!("{when}: {name}");
        if name.ends_with(".safetensors") {
            let meta = header(&path);
            let end = meta
                .as_object()
                .unwrap()
                .values()
                .filter_map(|t| t.get("data_offsets").and_then(|o| o[1].as_u64()))
                .max()
                .unwrap_or(0);
            let size = u64::from_le_bytes(bytes[..8].try_into().unwrap());
            assert_eq!(8 + size + end, bytes.len() as u64, "{what} is cut short");
        } else if name.ends_with(".csv") {
            let text = String::from_utf8(bytes).unwrap();
            let columns = text.lines().next().unwrap_or_default().split(',').count();
            assert!(text.ends_with('\n'), "{what} ends mid-line");
            assert!(text.lines().all(|l| l.split(',').count() == columns), "{what} has a partial row");
        } else if name.ends_with(".json") {
            serde_json::from_slice::<serde_json::Value>(&bytes).unwrap_or_else(|e| panic!("{what}: {e}"));
        }
    }
}

/// A safetensors file's JSON header.
fn header(path: &Path) -> serde_json::Value {
    let b = std::fs::read(path).unwrap();
    let size = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
    serde_json::from_slice(&b[8..8 + size]).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// A long-running command and how to read its progress.
struct Job<'a> {
    args: &'a [&'a str],
    /// Its output directory (`-o`) and the checkpoint file there.
    out: &'a str,
    checkpoint: &'a str,
    /// Steps or iterations of the whole run, and how long an uninterrupted one took.
    total: usize,
    within: Duration,
}

/// Runs the job in `dir` (with `--resume` once its checkpoint exists), killing it with SIGKILL
/// after a random 20-100% of the time the work left should take, until `kills` kills have
/// happened, then lets it finish. After every kill the files are whole, and the next run says
/// it resumed at the count `progress` reads from the checkpoint. Returns the counts it
/// resumed at.
fn kill_and_resume(dir: &Path, job: &Job, progress: impl Fn(&Path) -> usize, kills: usize) -> Vec<usize> {
    let seed: u64 = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64;
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let (out, checkpoint) = (job.out, dir.join(job.out).join(job.checkpoint));
    let mut resumed_at = Vec::new();
    for attempt in 0..=kills {
        let resume = checkpoint.exists();
        let expected = resume.then(|| progress(&checkpoint));
        let mut full: Vec<&str> = job.args.to_vec();
        full.extend(["-o", out]);
        if resume {
            full.push("--resume");
        }
        let mut child = command(dir, &full)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let left = 1.0 - expected.unwrap_or(0) as f64 / job.total as f64;
        if attempt < kills {
            std::thread::sleep(job.within.mul_f64(left * rng.random_range(0.2..1.0)));
            child.kill().unwrap();
        }
        let output = child.wait_with_output().unwrap();
        let text = String::from_utf8_lossy(&output.stderr).into_owned();
        let when = format!("seed {seed}, attempt {attempt}");
        assert_whole(&dir.join(out), &when);
        if let Some(n) = expected {
            // Only a run that got as far as reading its checkpoint says where it resumed.
            if let Some(line) = text.lines().find(|l| l.starts_with("resumed")) {
                let said = line.split_whitespace().any(|word| word == n.to_string());
                assert!(said, "{when}: the checkpoint is at {n}, but: {line}");
                resumed_at.push(n);
            }
        }
        if attempt == kills {
            assert!(output.status.success(), "{when}: the last run failed:\n{text}");
        }
    }
    resumed_at
}

#[test]
fn train_killed_at_random_moments_resumes_to_the_uninterrupted_weights() {
    let dir = workdir("kill-train");
    tiny_dataset(&dir);
    let args = ["train", "data", "--steps", "400"];
    let started = std::time::Instant::now();
    ok(&dir, &[&args[..], &["-o", "whole"]].concat());
    let within = started.elapsed();
    let step = |checkpoint: &Path| {
        header(checkpoint)["__metadata__"]["model"]
            .as_str()
            .map_or(0, |m| serde_json::from_str::<serde_json::Value>(m).unwrap()["step"].as_u64().unwrap() as usize)
    };
    let job = Job { args: &args, out: "killed", checkpoint: "checkpoint.safetensors", total: 400, within };
    let resumed = kill_and_resume(&dir, &job, step, 6);
    eprintln!("train resumed at steps {resumed:?}");
    // The README's promise: a resumed run ends with the same weights, bit for bit.
    assert!(
        tensor_bytes(&dir.join("whole/model.safetensors")) == tensor_bytes(&dir.join("killed/model.safetensors")),
        "killed and resumed training ended with other weights"
    );
    // Every logged step once, as in the uninterrupted run.
    let steps = |run: &str| -> Vec<usize> {
        let log = std::fs::read_to_string(dir.join(run).join("log.csv")).unwrap();
        log.lines().skip(1).map(|l| l.split(',').next().unwrap().parse().unwrap()).collect()
    };
    assert_eq!(steps("killed"), steps("whole"));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn track_train_killed_at_random_moments_continues_from_its_checkpoint() {
    let dir = workdir("kill-track");
    ok(&dir, &["motion", "generate", "--duration", "1.5", "--name", "w", "-o", "clips"]);
    let args = ["track", "train", "--clip", "clips/w.clip.safetensors", "--iterations", "60"];
    let started = std::time::Instant::now();
    ok(&dir, &[&args[..], &["-o", "whole"]].concat());
    let within = started.elapsed();
    let iteration =
        |checkpoint: &Path| header(checkpoint)["__metadata__"]["iteration"].as_str().unwrap().parse::<usize>().unwrap();
    let job = Job { args: &args, out: "run", checkpoint: "policy.safetensors", total: 60, within };
    let resumed = kill_and_resume(&dir, &job, iteration, 6);
    eprintln!("track train resumed at iterations {resumed:?}");
    // Every iteration is logged once, in order: nothing after a checkpoint survives a kill.
    let log = std::fs::read_to_string(dir.join("run/log.csv")).unwrap();
    let its: Vec<usize> = log.lines().skip(1).map(|l| l.split(',').next().unwrap().parse().unwrap()).collect();
    assert_eq!(its, (1..=60).collect::<Vec<_>>());
    assert_eq!(iteration(&dir.join("run/policy.safetensors")), 60);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_trajectory_model_trains_alike_on_1_and_2_threads() {
    let dir = workdir("threads");
    tiny_dataset(&dir);
    for threads in ["1", "2"] {
        let out = command(&dir, &["train", "data", "-o", threads])
            .env("RAYON_NUM_THREADS", threads)
            .env("MATMUL_NUM_THREADS", threads)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    }
    assert!(
        tensor_bytes(&dir.join("1/model.safetensors")) == tensor_bytes(&dir.join("2/model.safetensors")),
        "1 and 2 threads trained different weights"
    );
    std::fs::remove_dir_all(&dir).ok();
}
