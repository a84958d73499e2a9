//! The `flowmimic` binary end to end on the `tiny` preset: the stages hand files to each other
//! exactly as a user's commands do.

mod common;

use common::{flowmimic, ok, tensor_bytes, workdir};
use std::path::Path;
use std::process::Command;

#[test]
fn stages_connect_through_their_files() {
    let dir = workdir("stages");
    let table = ok(&dir, &["motion", "generate", "--duration", "1.5", "--name", "w", "-o", "clips"]);
    assert!(table.contains("w ") && dir.join("clips/w.clip.safetensors").exists(), "{table}");
    let train = ok(&dir, &["track", "train", "--clip", "clips/w.clip.safetensors", "-o", "run", "--iterations", "2"]);
    assert!(train.contains("[    2/2]"), "{train}");
    for file in ["policy.safetensors", "clip.safetensors", "log.csv", "config.json", "reward.png", "body_error.svg"] {
        assert!(dir.join("run").join(file).exists(), "run/{file} missing");
    }
    // Each reward term's mean per iteration is a column of the log.
    let log = std::fs::read_to_string(dir.join("run/log.csv")).unwrap();
    let (header, row) = (log.lines().next().unwrap(), log.lines().nth(1).unwrap());
    assert!(header.ends_with("reward_action_rate,reward_joint_limit"), "{header}");
    assert_eq!(header.split(',').count(), row.split(',').count(), "{header}\n{row}");
    // Training again into the same run without --resume is refused; with it, it continues.
    let (success, text) = flowmimic(&dir, &["track", "train", "--clip", "clips/w.clip.safetensors", "-o", "run"]);
    assert!(!success && text.contains("--resume"), "{text}");
    let resumed = ok(
        &dir,
        &["track", "train", "--clip", "clips/w.clip.safetensors", "-o", "run", "--resume", "--iterations", "3"],
    );
    assert!(resumed.contains("resumed") && resumed.contains("[    3/3]"), "{resumed}");
    // Without --clip, a resumed run tracks its own clip.
    let resumed = ok(&dir, &["track", "train", "-o", "run", "--resume", "--iterations", "4"]);
    assert!(resumed.contains("resumed") && resumed.contains("[    4/4]"), "{resumed}");
    let warm = ok(
        &dir,
        &["track", "train", "--clip", "clips/w.clip.safetensors", "-o", "warm", "--init", "run", "--iterations", "1"],
    );
    assert!(
        warm.contains("starting from the policy of run/policy.safetensors") && warm.contains("[    1/1]"),
        "{warm}"
    );
    let eval = ok(&dir, &["track", "eval", "run", "--episodes", "2"]);
    assert!(eval.contains("\"clip\":\"w\"") && eval.contains("\"clip_steps\":45"), "{eval}");
    assert!(eval.contains("\"root_path_error\":") && eval.contains("\"end_heading_error\":"), "{eval}");
    let later = ok(&dir, &["track", "eval", "run", "--episodes", "2", "--start-frame", "20"]);
    assert!(later.contains("\"start_frame\":20") && later.contains("\"clip_steps\":45"), "{later}");
    // Each failed episode names the frame it ended at, after its start; the table says when.
    let report: serde_json::Value = serde_json::from_str(later.lines().find(|l| l.starts_with('{')).unwrap()).unwrap();
    let frames: Vec<u64> = report["failure_frames"].as_array().unwrap().iter().map(|f| f.as_u64().unwrap()).collect();
    let failed = (2.0 * (1.0 - report["success_rate"].as_f64().unwrap())).round() as usize;
    assert!(frames.len() == failed && frames.iter().all(|f| (21..=45).contains(f)), "{later}");
    assert!(later.contains("fails at (clip second x episodes)"), "{later}");
    let (success, text) = flowmimic(&dir, &["track", "eval", "run", "--start-frame", "45"]);
    assert!(!success && text.contains("start frame 45") && text.contains("clip w"), "{text}");
    let collect = ok(&dir, &["collect", "run", "-o", "data"]);
    assert!(collect.contains("steps/s") && collect.contains("fall rate"), "{collect}");
    // An expert on a clip named on the command line (a shipped expert holds none), and the
    // clip pairing refused where it would be ambiguous.
    ok(&dir, &["motion", "generate", "--duration", "1.0", "--name", "v", "--speed", "0.8", "-o", "clips"]);
    let paired = ok(&dir, &["collect", "run", "--clip", "clips/v.clip.safetensors", "-o", "data-v"]);
    assert!(paired.contains("collecting v ") && paired.contains("holds 1 clips"), "{paired}");
    ok(&dir, &["motion", "mirror", "clips/v.clip.safetensors", "-o", "clips"]);
    assert!(dir.join("clips/v-mirrored.clip.safetensors").exists());
    let mirror = ok(&dir, &["dataset", "mirror", "data-v"]);
    assert!(mirror.contains("added 1 mirrored clips") && dir.join("data-v/v-mirrored.rollouts.safetensors").exists());
    assert!(ok(&dir, &["dataset", "mirror", "data-v"]).contains("added 0 mirrored clips"), "mirrored once");
    let (success, text) = flowmimic(&dir, &["collect", "run", "warm", "--clip", "clips/v.clip.safetensors"]);
    assert!(!success && text.contains("--clip pairs clips with one expert run"), "{text}");
    let (success, text) = flowmimic(&dir, &["collect", "run", "--clip", "clips/missing.clip.safetensors"]);
    assert!(!success && text.contains("missing.clip.safetensors"), "{text}");
    let inspect = ok(&dir, &["dataset", "inspect", "data"]);
    assert!(inspect.contains("feature ranges") && dir.join("data/coverage_root_speed.png").exists(), "{inspect}");
    assert!(inspect.contains("backward") && dir.join("data/coverage_yaw_rate.png").exists(), "{inspect}");
    // Coverage and falls per clip as well as in total.
    let per_clip = inspect.lines().filter(|l| l.starts_with("w ") && l.ends_with('%')).count();
    assert!(inspect.contains("sidestepping   aside L/R  reversing  fall rate") && per_clip == 1, "{inspect}");
    assert!(
        inspect.contains("hand height (m)   left    right   higher") && inspect.contains("a hand above 1.1 m in"),
        "{inspect}"
    );
    assert!(inspect.contains("the right hand below 0.7 m in"), "{inspect}");
    let stats = ok(&dir, &["dataset", "stats", "data", "--history", "2", "--horizon", "3"]);
    assert!(stats.contains("windows") && dir.join("data/stats-N2-H3.safetensors").exists(), "{stats}");
    trajectory_model_trains_resumes_and_drives(&dir);
    std::fs::remove_dir_all(&dir).ok();
}

/// A model told each window's task: trained on clips labelled by name, refused where no clip
/// is a reaching one, and driven on a walking and a reaching task.
fn task_labelled_model_trains_and_drives(dir: &Path) {
    let labels = |clips: &str| format!("[model]\ntask_labels = true\n[train]\nreach_clips = [{clips}]\n");
    std::fs::write(dir.join("labels.toml"), labels("\"v-mirrored\"")).unwrap();
    std::fs::write(dir.join("no-reach.toml"), labels("\"reach_\"")).unwrap();
    let train = |config: &str| {
        flowmimic(dir, &["--config", config, "train", "data-v", "--objective", "fm", "-o", "labelled", "--steps", "20"])
    };
    let (refused, text) = train("no-reach.toml");
    assert!(!refused && text.contains("data-v") && text.contains("train.reach_clips"), "{text}");
    let (trained, text) = train("labels.toml");
    assert!(
        trained && text.contains("task labels: reach on 1 of 2 clips (50% of") && text.contains("tokens"),
        "{text}"
    );
    for (task, told) in [("joystick", "task label walk"), ("reach", "task label reach")] {
        let out = format!("labelled-{task}.rollout.safetensors");
        let run =
            ok(dir, &["run", "--model", "labelled", "--task", task, "--seconds", "0.3", "--envs", "2", "-o", &out]);
        assert!(run.contains("environments fell") && run.contains(told), "{run}");
    }
    // A model told each window's motion, driven told the joystick's command at twice its
    // weight (classifier-free guidance, two network calls a step).
    std::fs::write(dir.join("commands.toml"), "[model]\ncommand_labels = true\n").unwrap();
    let args =
        ["--config", "commands.toml", "train", "data-v", "--objective", "fm", "-o", "commanded", "--steps", "20"];
    let trained = ok(dir, &args);
    assert!(trained.contains("command labels: each window's motion"), "{trained}");
    let args = ["run", "--model", "commanded", "--task", "joystick", "--label-scale", "2", "--seconds", "0.3"];
    let run = ok(dir, &[&args[..], &["--envs", "2", "-o", "commanded.rollout.safetensors"]].concat());
    assert!(run.contains("told the command") && run.contains("label scale 2 (flag)"), "{run}");
}

/// `train` and `run` on the tiny dataset that `collect` wrote.
fn trajectory_model_trains_resumes_and_drives(dir: &Path) {
    let train = ok(dir, &["train", "data", "--objective", "fm", "-o", "fm"]);
    assert!(train.contains("parameters") && train.contains("[   60/60]"), "{train}");
    for file in ["model.safetensors", "stats.safetensors", "checkpoint.safetensors", "log.csv", "loss.png"] {
        assert!(dir.join("fm").join(file).exists(), "fm/{file} missing");
    }
    // The training loss falls (first logged mean vs last).
    let log = std::fs::read_to_string(dir.join("fm/log.csv")).unwrap();
    let losses: Vec<f64> = log.lines().skip(1).map(|l| l.split(',').nth(1).unwrap().parse().unwrap()).collect();
    assert!(losses.len() == 3 && losses[2] < 0.9 * losses[0], "losses {losses:?}");
    // Same seed, same weights; a run stopped at 20 steps and resumed to 60 ends bit-identical.
    ok(dir, &["train", "data", "--objective", "fm", "-o", "fm-part", "--steps", "20"]);
    let (refused, text) = flowmimic(dir, &["train", "data", "--objective", "fm", "-o", "fm-part"]);
    assert!(!refused && text.contains("--resume"), "{text}");
    let (refused, text) = flowmimic(dir, &["train", "data", "--objective", "ddpm", "-o", "fm-part", "--resume"]);
    assert!(!refused && text.contains("objective fm"), "{text}");
    // So does the same objective with another setting (here, what the network predicts).
    std::fs::write(dir.join("clean.toml"), "[train]\nflow_prediction = \"sample\"\n").unwrap();
    let (refused, text) =
        flowmimic(dir, &["--config", "clean.toml", "train", "data", "--objective", "fm", "-o", "fm-part", "--resume"]);
    assert!(!refused && text.contains("prediction: Sample"), "{text}");
    // And another learning rate: a resumed run may change only its length.
    std::fs::write(dir.join("lr.toml"), "[train]\nlr = 0.0005\n").unwrap();
    let (refused, text) =
        flowmimic(dir, &["--config", "lr.toml", "train", "data", "--objective", "fm", "-o", "fm-part", "--resume"]);
    assert!(!refused && text.contains("train.lr") && text.contains("(now 0.0005)"), "{text}");
    ok(dir, &["train", "data", "--objective", "fm", "-o", "fm-part", "--resume"]);
    let tensors = |p: &str| tensor_bytes(&dir.join(p));
    assert!(tensors("fm/model.safetensors") == tensors("fm-part/model.safetensors"), "resume is not exact");
    let ddpm = ok(dir, &["train", "data", "--objective", "ddpm", "-o", "ddpm"]);
    assert!(ddpm.contains("DDPM Transformer"), "{ddpm}");
    // A model trained for another window refuses to resume on these settings.
    std::fs::write(dir.join("longer.toml"), "[model]\nhorizon = 3\n").unwrap();
    let (refused, text) = flowmimic(dir, &["--config", "longer.toml", "train", "data", "-o", "fm", "--resume"]);
    assert!(!refused && text.contains("checkpoint.safetensors") && text.contains("horizon: 3"), "{text}");
    // MeanFlow trains with its loss falling, on tokens of state, action and next state, with a
    // network that predicts the clean sample (the shipped one-step model's settings).
    std::fs::write(
        dir.join("sas.toml"),
        "[model]\npairing = \"state-action-state\"\n[train]\nflow_prediction = \"sample\"\n",
    )
    .unwrap();
    let meanflow = ok(dir, &["--config", "sas.toml", "train", "data", "--objective", "meanflow", "-o", "meanflow"]);
    assert!(
        meanflow.contains("MEANFLOW (clean sample) Transformer") && meanflow.contains("tokens of 399:"),
        "{meanflow}"
    );
    let log = std::fs::read_to_string(dir.join("meanflow/log.csv")).unwrap();
    let losses: Vec<f64> = log.lines().skip(1).map(|l| l.split(',').nth(1).unwrap().parse().unwrap()).collect();
    assert!(losses[2] < 0.95 * losses[0], "MeanFlow losses {losses:?}");
    // MeanFlow's two times and state-action-state tokens export too.
    let text = ok(dir, &["export", "meanflow", "-o", "meanflow.onnx", "--check", "meanflow.check.safetensors"]);
    assert!(text.contains("meanflow denoiser, opset 17") && dir.join("meanflow.check.safetensors").exists(), "{text}");
    task_labelled_model_trains_and_drives(dir);
    // Every objective drives the humanoid (MeanFlow in one step); the rollout holds every step.
    for (model, nfe) in [("fm", "5"), ("ddpm", "5"), ("meanflow", "1")] {
        let out = format!("{model}.rollout.safetensors");
        let args = [
            "run",
            "--model",
            model,
            "--task",
            "joystick",
            "--seconds",
            "0.5",
            "--envs",
            "2",
            "--nfe",
            nfe,
            "-o",
            &out,
        ];
        let run = ok(dir, &args);
        assert!(run.contains("environments fell") && dir.join(&out).exists(), "{run}");
    }
    // Inverse dynamics fits to the same data, lands in the model directory, and drives.
    let text = ok(dir, &["inverse", "data", "--model", "fm", "--steps", "200"]);
    assert!(text.contains("[  200/200]") && dir.join("fm/inverse-log.csv").exists(), "{text}");
    let log = std::fs::read_to_string(dir.join("fm/inverse-log.csv")).unwrap();
    let errors: Vec<f64> = log.lines().skip(1).map(|l| l.split(',').nth(1).unwrap().parse().unwrap()).collect();
    assert!(errors.len() == 2 && errors[1] < errors[0], "inverse-dynamics errors {errors:?}");
    let args = ["run", "--model", "fm", "--task", "joystick", "--seconds", "0.5", "--inverse-dynamics", "0.5"];
    let run = ok(dir, &[&args[..], &["-o", "id.rollout.safetensors"]].concat());
    assert!(run.contains("environments fell") && dir.join("id.rollout.safetensors").exists(), "{run}");
    let (refused, text) = flowmimic(dir, &["run", "--model", "ddpm", "--inverse-dynamics", "0.5"]);
    assert!(!refused && text.contains("no inverse.safetensors"), "{text}");
    exports_match_flowmimic_in_onnx_runtime(dir);
    // Rendering needs EGL (Mesa's software OpenGL); where the machine has none, the error
    // says what to install.
    let (rendered, text) = flowmimic(dir, &["render", "fm.rollout.safetensors", "--width", "64", "--height", "48"]);
    if rendered {
        assert!(
            dir.join("runs/render/fm.rollout.gif").exists() && dir.join("runs/render/fm.rollout_sheet.png").exists(),
            "{text}"
        );
    } else {
        assert!(text.contains("libegl1"), "{text}");
        eprintln!("rendering not checked here: {text}");
    }
    viewer_serves_and_draws(dir, "fm.rollout.safetensors");
    let (refused, text) = flowmimic(dir, &["render", "fm.rollout.safetensors", "--env", "5"]);
    assert!(!refused && text.contains("2 environments"), "{text}");
    // Evaluations write their raw trials, summary, plot and report, and reuse stored points.
    let models = ["--model", "fm=fm", "--model", "ddpm=ddpm"];
    let survival =
        [&["eval", "survival", "--nfe", "1,2", "--trials", "2", "--seconds", "0.5", "-o", "eval"], &models[..]]
            .concat();
    let text = ok(dir, &survival);
    assert!(text.contains("| fm | fm | 2 |") && text.contains("| ddpm | ddpm | 1 |"), "{text}");
    for file in ["survival.csv", "survival.json", "survival.png", "survival.svg", "report.md"] {
        assert!(dir.join("eval").join(file).exists(), "eval/{file} missing");
    }
    assert_eq!(std::fs::read_to_string(dir.join("eval/survival.csv")).unwrap().lines().count(), 1 + 2 * 2 * 2);
    assert!(ok(dir, &survival).contains("reusing 2 stored trials"));
    // Another episode length is another experiment: nothing stored is reused for it.
    let longer: Vec<&str> = survival.iter().map(|a| if *a == "0.5" { "0.6" } else { a }).collect();
    assert!(!ok(dir, &longer).contains("reusing"), "a stored result answered another episode length");
    // The guidance effect on the executed action, both ways of taking the gradient.
    let text = ok(dir, &["eval", "guidance", "--model", "fm=fm", "--scales", "3", "--samples", "2", "-o", "eval"]);
    assert!(
        text.contains("through-network") && text.contains("cost-only") && dir.join("eval/guidance.json").exists(),
        "{text}"
    );
    let text = ok(dir, &["eval", "joystick", "--model", "fm=fm", "--scales", "0,10", "--trials", "1", "-o", "eval"]);
    assert!(text.contains("velocity RMSE") && dir.join("eval/joystick.png").exists(), "{text}");
    // Each row's RMSE as a share of the unguided one (the w 0 row's own is 1).
    let cells = |row: &str| row.split('|').map(|c| c.trim().to_string()).collect::<Vec<_>>();
    let rows: Vec<_> = text.lines().filter(|l| l.starts_with("| fm |")).map(cells).collect();
    let rmse = |c: &[String]| c[4].split(' ').next().unwrap().parse::<f64>().unwrap();
    assert_eq!(rows[0][5], "1.000", "{text}");
    let share: f64 = rows[1][5].parse().unwrap();
    assert!((share - rmse(&rows[1]) / rmse(&rows[0])).abs() < 2e-3, "{text}");
    // Another schedule, segment by segment; more segments than the table holds are refused.
    let schedule = ["eval", "joystick", "--model", "fm=fm", "--scales", "0", "--trials", "1", "-o", "eval"];
    let text = ok(dir, &[&schedule[..], &["--schedule", "1:0.5,0,0;1:0,0,0.3"]].concat());
    assert!(text.contains("| 1 | +0.50, +0.00, +0.00 |") && text.contains("| 2 | +0.00, +0.00, +0.30 |"), "{text}");
    assert!(text.contains("| achieved | planned | followed | falls |"), "{text}");
    let (refused, text) = flowmimic(dir, &[&schedule[..], &["--schedule", &["1:0,0,0"; 9].join(";")]].concat());
    assert!(!refused && text.contains("1 to 8 segments, not 9"), "{text}");
    // Reaching while standing starts from a standing clip and reports the median time to reach.
    let standing = ["eval", "reach", "--standing", "--model", "fm=fm", "--scales", "0", "--trials", "2", "-o", "eval"];
    let text = ok(dir, &standing);
    assert!(text.contains("| within 0.10 m | planned within 0.10 m | median time to reach (s) |"), "{text}");
    // Low targets are reported apart: the row's share of them is the CSV's, trial by trial.
    let csv = std::fs::read_to_string(dir.join("eval/reach-standing.csv")).unwrap();
    let column = |name: &str| -> Vec<f64> {
        let at = csv.lines().next().unwrap().split(',').position(|c| c == name).expect(name);
        csv.lines().skip(1).map(|l| l.split(',').nth(at).unwrap().parse().unwrap()).collect()
    };
    let low = column("low");
    let share = 100.0 * low.iter().sum::<f64>() / low.len() as f64;
    assert!(text.contains("| targets below 0.9 m: within 0.10 m / planned / falls |"), "{text}");
    // Every trial records where its plans put the hand, unguided too.
    assert!(column("planned_closest").iter().all(|d| d.is_finite()), "{csv}");
    assert!(text.contains(&format!(" of {share:.0}% |")), "{share}% low in the CSV:\n{text}");
    // Two models in one sweep, each at its own recommended.toml's settings.
    std::fs::write(dir.join("fm/recommended.toml"), "[waypoint]\nguidance_scale = 10.0\ninverse_dynamics = 0.5\n")
        .unwrap();
    std::fs::write(dir.join("ddpm/recommended.toml"), "[waypoint]\nnfe = 2\nguidance_scale = 20.0\n").unwrap();
    let text = ok(dir, &["eval", "waypoint", "--model", "fm=fm", "--model", "ddpm", "--trials", "1", "-o", "eval"]);
    assert!(text.contains("| arrived |") && dir.join("eval/waypoint.csv").exists(), "{text}");
    let rows: Vec<String> = text
        .lines()
        .filter(|l| l.starts_with("| fm |") || l.starts_with("| ddpm |"))
        .map(|l| l.split('|').take(3).collect::<Vec<_>>().join("|").trim().to_string())
        .collect();
    assert_eq!(rows, ["| fm | 0", "| fm | 10", "| ddpm | 0", "| ddpm | 20"], "{text}");
    let report = std::fs::read_to_string(dir.join("eval/report.md")).unwrap();
    assert!(
        report.contains("at NFE 5, adaptive off, inverse dynamics 0.5, start actions pd-targets; `ddpm`")
            && report.contains("at NFE 2, adaptive off, inverse dynamics 0, start actions pd-targets."),
        "{report}"
    );
    let json = std::fs::read_to_string(dir.join("eval/waypoint.json")).unwrap();
    assert_eq!(json.matches("\"inverse_dynamics\": 0.5").count(), 2, "{json}");
    for file in ["fm", "ddpm"] {
        std::fs::remove_file(dir.join(file).join("recommended.toml")).unwrap();
    }
    // Guiding the last solver step too is another point: measured anew and said in the report.
    let last = ["eval", "joystick", "--model", "fm=fm", "--scales", "10", "--trials", "1", "-o", "eval"];
    let text = ok(dir, &[&last[..], &["--guidance-interval", "0:5"]].concat());
    assert!(!text.contains("reusing"), "a stored result answered another guidance interval: {text}");
    assert!(text.contains("| 10 | ") && text.contains(" | - | "), "no unguided point to divide by: {text}");
    let report = std::fs::read_to_string(dir.join("eval/report.md")).unwrap();
    assert!(report.contains("start actions pd-targets, guidance on solver steps 0 to 4."), "{report}");
    let (refused, text) = flowmimic(dir, &[&last[..], &["--guidance-interval", "0:9"]].concat());
    assert!(!refused && text.contains("need start < end <= NFE (5)"), "{text}");
    let (refused, text) = flowmimic(dir, &["run", "--model", "fm", "--task", "reach", "--target", "1,NaN,1"]);
    assert!(!refused && text.contains("NaN"), "{text}");
    let (refused, text) = flowmimic(dir, &["run", "--model", "fm", "--task", "joystick", "--schedule", "3:9,0,0"]);
    assert!(!refused && text.contains("joystick speed"), "{text}");
    // A run too short for one control step is refused, not written as an empty rollout.
    let (refused, text) =
        flowmimic(dir, &["run", "--model", "fm", "--seconds", "0.01", "-o", "empty.rollout.safetensors"]);
    assert!(!refused && text.contains("duration") && !dir.join("empty.rollout.safetensors").exists(), "{text}");
    // A clip is told from a rollout by its format, whatever its file name.
    viewer_serves_and_draws(dir, "clips/w.clip.safetensors");
}

/// `flowmimic export` of the tiny model and expert; where Python has numpy and onnxruntime
/// (`make test` installs them into third_party/python), ONNX Runtime reproduces flowmimic's
/// outputs (`examples/onnx_check.py`). Bad input is refused without writing anything.
fn exports_match_flowmimic_in_onnx_runtime(dir: &Path) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let pythonpath = root.join("third_party/python");
    let python = |args: &[&std::ffi::OsStr]| {
        Command::new("python3").args(args).current_dir(dir).env("PYTHONPATH", &pythonpath).output()
    };
    let has_runtime = python(&["-c".as_ref(), "import numpy, onnxruntime".as_ref()]).is_ok_and(|o| o.status.success());
    // The model's check includes the conditioning built from a rollout, as the controller does.
    let rollout = ["--rollout", "fm.rollout.safetensors", "--step", "5"];
    let labelled = ["--rollout", "labelled-reach.rollout.safetensors", "--step", "5"];
    let graphs = [("model", "fm", &rollout[..]), ("labelled", "labelled", &labelled[..]), ("expert", "run", &[])];
    for (what, source, extra) in graphs {
        let (graph, check) = (format!("{what}.onnx"), format!("{what}.check.safetensors"));
        let text = ok(dir, &[&["export", source, "-o", &graph, "--check", &check][..], extra].concat());
        assert!(text.contains("opset 17") || text.contains("actor"), "{text}");
        if has_runtime {
            let script = root.join("examples/onnx_check.py");
            let mut args = vec![script.as_os_str(), graph.as_ref(), check.as_ref()];
            args.extend(extra.get(1).map(std::ffi::OsStr::new));
            let out = python(&args).unwrap();
            let report = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
            assert!(out.status.success() && report.contains("relative error"), "{report}");
            assert!(extra.is_empty() || report.contains("conditioning from the rollout"), "{report}");
        }
    }
    if !has_runtime {
        eprintln!("ONNX Runtime check skipped: python3 cannot import numpy and onnxruntime (scripts/fetch-pydeps.sh)");
    }
    std::fs::create_dir_all(dir.join("broken")).unwrap();
    std::fs::write(dir.join("broken/model.safetensors"), b"damaged").unwrap();
    for (source, says) in [("broken", "model.safetensors"), ("data", "neither a model directory")] {
        let (refused, text) = flowmimic(dir, &["export", source, "-o", "refused.onnx"]);
        assert!(!refused && text.contains(says) && !dir.join("refused.onnx").exists(), "{text}");
    }
}

/// Every shipped model (Flow Matching of velocity and of the clean sample, MeanFlow, DDPM;
/// state-action and state-action-state tokens) exports, and where ONNX Runtime is installed,
/// its graph and the sampler `examples/onnx_check.py` writes out for its objective reproduce
/// flowmimic's outputs and samples.
#[test]
fn every_shipped_model_exports_and_samples_as_flowmimic_in_onnx_runtime() {
    let dir = workdir("export-shipped");
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let pythonpath = root.join("third_party/python");
    let python =
        |args: &[&str]| Command::new("python3").args(args).current_dir(&dir).env("PYTHONPATH", &pythonpath).output();
    let has_runtime = python(&["-c", "import numpy, onnxruntime"]).is_ok_and(|o| o.status.success());
    let mut exported = 0;
    for entry in std::fs::read_dir(root.join("pretrained/models")).unwrap() {
        let model = entry.unwrap().path();
        let name = model.file_name().unwrap().to_string_lossy().into_owned();
        let (graph, check) = (format!("{name}.onnx"), format!("{name}.check.safetensors"));
        ok(&dir, &["export", model.to_str().unwrap(), "-o", &graph, "--check", &check]);
        exported += 1;
        if has_runtime {
            let script = root.join("examples/onnx_check.py");
            let out = python(&[script.to_str().unwrap(), &graph, &check]).unwrap();
            let report = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
            assert!(out.status.success() && report.contains("samples, NFE 5"), "{name}: {report}");
        }
    }
    assert!(exported >= 7, "{exported} models");
    if !has_runtime {
        eprintln!("ONNX Runtime check skipped: python3 cannot import numpy and onnxruntime (scripts/fetch-pydeps.sh)");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn every_config_layer_in_configs_is_valid() {
    // The recipes in configs/ are what the docs' commands layer over a preset: a key renamed in
    // the code must not leave one of them refused.
    let dir = workdir("configs");
    let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
    let mut checked = 0;
    for entry in std::fs::read_dir(&configs).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            ok(&dir, &["--config", path.to_str().unwrap(), "config"]);
            checked += 1;
        }
    }
    assert!(checked >= 10, "only {checked} configs found in {}", configs.display());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_input_is_a_clear_error_not_a_crash() {
    let dir = workdir("bad-input");
    std::fs::write(dir.join("bad.bvh"), "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0\n").unwrap();
    let (success, text) = flowmimic(&dir, &["motion", "import", "bad.bvh"]);
    assert!(!success && text.contains("bad.bvh") && text.contains("line"), "{text}");
    std::fs::write(dir.join("typo.toml"), "[track]\nenvz = 3\n").unwrap();
    let (success, text) = flowmimic(&dir, &["--config", "typo.toml", "config"]);
    assert!(!success && text.contains("envz"), "{text}");
    let (success, text) = flowmimic(&dir, &["track", "eval", "no-such-run"]);
    assert!(!success && text.contains("no-such-run"), "{text}");
    assert_eq!(text.matches("No such file").count(), 1, "the cause is said once: {text}");
    let fm = format!("fm={}", concat!(env!("CARGO_MANIFEST_DIR"), "/../../pretrained/models/fm"));
    let (success, text) = flowmimic(&dir, &["eval", "reach", "--model", &fm, "--heights", "1.5,0.9", "--quick"]);
    assert!(!success && text.contains("--heights") && text.contains("LOW <= HIGH"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

/// What a newcomer tripped on, trying the binary from a folder outside the checkout: numbers
/// that mean nothing are refused at the command line, files of the wrong kind are named with
/// the kind expected and the command that makes it, one bad file does not stop the others, a
/// cause is said once, outputs land under runs/, a closed pipe ends the command quietly, and
/// the shipped model is found from anywhere.
#[test]
fn a_newcomers_mistakes_get_clear_answers() {
    let dir = workdir("newcomer");
    let refused = |args: &[&str], words: &[&str]| {
        let (success, text) = flowmimic(&dir, args);
        assert!(!success, "{args:?} succeeded:\n{text}");
        for w in words {
            assert!(text.contains(w), "{args:?}: no '{w}' in:\n{text}");
        }
        text
    };
    refused(&["run", "--seconds", "-2"], &["-2 s", "above 0"]);
    refused(&["sim", "hold", "--seconds=-1"], &["-1 s", "above 0"]);
    refused(&["run", "--envs", "0"], &["0 environments", "1 to 4096"]);
    refused(&["run", "--envs", "100000"], &["100000 environments"]);
    refused(&["track", "train", "--iterations", "0"], &["at least 1"]);
    let experts = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../pretrained/experts");
    let (straight, ahead) = (experts.join("walk_straight"), experts.join("stand-ahead"));
    let plans = ["track", "plan-clips", straight.to_str().unwrap(), "--clip", "nothing.clip.safetensors", "-o", "p"];
    refused(&plans, &["nothing.clip.safetensors"]);
    refused(&["run", "--executor", ahead.to_str().unwrap(), "--seconds", "0.2"], &["stand-ahead", "ahead"]);
    let model = experts.join("../models/fm");
    refused(&["eval", "survival", "--trials", "1", "--executor", model.to_str().unwrap()], &["not a tracking run"]);
    refused(&["run", "--executor", "nowhere", "--seconds", "0.2"], &["executor nowhere", "no such tracking run"]);
    let executor = experts.join("executor-walks");
    refused(
        &["run", "--executor", executor.to_str().unwrap(), "--executor-residual", "-1"],
        &["-1", "share from 0 to 1"],
    );
    let cosine = experts.join("../models/fm-cosine");
    let plain = ["run", "--model", cosine.to_str().unwrap(), "--seconds", "0.2", "-o", "x.rollout.safetensors"];
    let unused = ok(&dir, &[&plain[..], &["--executor-residual", "0.5"]].concat());
    assert!(unused.contains("not used without an executor"), "{unused}");
    // A model's recommended executor is taken, and `none` turns it off.
    let walks = experts.join("../models/fm-walks");
    let walks = walks.to_str().unwrap();
    let taken = ok(&dir, &["run", "--model", walks, "--seconds", "0.2", "-o", "x.rollout.safetensors"]);
    assert!(taken.contains("executor-walks (model)") && taken.contains("executor residual 0.5 (model)"), "{taken}");
    let off =
        ok(&dir, &["run", "--model", walks, "--executor", "none", "--seconds", "0.2", "-o", "x.rollout.safetensors"]);
    assert!(off.contains("executor none (flag)") && !off.contains("plans executed by"), "{off}");
    let zero = ok(
        &dir,
        &["run", "--model", walks, "--executor-residual", "0", "--seconds", "0.2", "-o", "x.rollout.safetensors"],
    );
    assert!(zero.contains("residual 0 executes the plans' own actions"), "{zero}");
    // An expert of clips is a valid policy, but not an executor: said, not refused.
    let expert = experts.join("walks-pushes");
    let noted =
        ok(&dir, &["run", "--executor", expert.to_str().unwrap(), "--seconds", "0.2", "-o", "x.rollout.safetensors"]);
    assert!(noted.contains("not trained as one"), "{noted}");
    refused(&["run", "--acceleration", "-1", "--seconds", "0.2"], &["acceleration = -1", "0 or more"]);
    refused(&["run", "--label-scale", "2", "--seconds", "0.2"], &["label scale 2", "no labels"]);
    // Files of the wrong kind.
    std::fs::write(dir.join("picture.png"), b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR").unwrap();
    refused(&["motion", "import", "picture.png"], &["picture.png", "not a BVH or DeepMimic", "PNG image"]);
    let bvh = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/mocap/02_01.bvh");
    let bvh = bvh.to_str().unwrap();
    refused(&["render", bvh], &["BVH motion capture", "motion import"]);
    refused(&["track", "train", "--clip", bvh], &["not a clip", "BVH motion capture", "motion import"]);
    let shipped = |p: &str| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../pretrained").join(p);
    let expert = shipped("experts/walk_straight");
    refused(&["run", "--model", expert.to_str().unwrap()], &["tracking expert", "not a trajectory model"]);
    let wander = shipped("experts/wander_3");
    refused(&["track", "eval", wander.to_str().unwrap()], &["--clip", "motion corpus"]);
    // One bad file is reported once and the good one still imported.
    std::fs::write(dir.join("bad.bvh"), "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0\n").unwrap();
    let text = refused(&["motion", "import", "bad.bvh", bvh, "-o", "clips"], &["1 of 2 files"]);
    assert!(dir.join("clips/02_01.clip.safetensors").exists(), "{text}");
    let (_, single) = flowmimic(&dir, &["motion", "import", "bad.bvh"]);
    let cause = single.lines().find(|l| l.contains("line")).unwrap_or_default().to_string();
    assert_eq!(single.matches("line ").count(), 1, "the cause is said once: {single}");
    assert!(!cause.is_empty(), "{single}");
    // Outputs land under runs/, not beside a (maybe shipped) input.
    ok(&dir, &["motion", "inspect", "clips/02_01.clip.safetensors"]);
    assert!(dir.join("runs/inspect/coverage_forward.png").exists() && !dir.join("clips/coverage_forward.png").exists());
    // The shipped model from a folder outside the checkout, without --model; a pipe closed
    // before the output ends the command as SIGPIPE does (`flowmimic run | head`), not with
    // a panic.
    let mut child = common::command(&dir, &["run", "--task", "joystick", "--seconds", "0.5", "--envs", "2"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("the shipped default") && !stderr.contains("panicked"), "{stderr}");
    const SIGPIPE: i32 = 13;
    assert_eq!(std::os::unix::process::ExitStatusExt::signal(&out.status), Some(SIGPIPE), "{stderr}");
    // The outcome of the task, after a run and from a saved rollout.
    let run = ok(&dir, &["run", "--task", "joystick", "--seconds", "1.2", "-o", "j.rollout.safetensors"]);
    let outcome = ok(&dir, &["eval", "outcome", "j.rollout.safetensors"]);
    assert!(run.contains("followed") && run.contains("+1.0, +0.0, +0.0"), "{run}");
    // Segments the run never reached are said once, not printed as empty rows.
    assert!(run.contains("ended before its last 3 segments") && !run.contains("-0.5, +0.0, +0.0"), "{run}");
    assert!(run.contains("the schedule is 12 s long") && outcome.contains("followed"), "{run}\n{outcome}");
    // The model's recommended settings where a flag is absent, each said with its source.
    assert!(run.contains("NFE 2 (model), w 50 (model), adaptive 1.5 (model)"), "{run}");
    let flagged = ok(&dir, &["run", "--seconds", "0.2", "--nfe", "1", "-o", "w.rollout.safetensors"]);
    // An unguided walk names no guidance setting.
    assert!(flagged.contains("settings for walk: NFE 1 (flag), inverse dynamics"), "{flagged}");
    assert!(!flagged.contains("w 10") && !flagged.contains("adaptive"), "{flagged}");
    // A port in use is said once.
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port().to_string();
    let text = refused(&["play", "--port", &port], &["cannot listen"]);
    assert_eq!(text.matches("in use").count(), 1, "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn the_pipeline_runs_every_stage_then_skips_what_is_done() {
    let dir = workdir("pipeline");
    let first = ok(&dir, &["pipeline", "-o", "p"]);
    assert!(first.contains("== train ddpm: done") && first.contains("pipeline finished"), "{first}");
    assert!(dir.join("p/eval/report.md").exists() && dir.join("p/eval/survival.png").exists());
    assert!(dir.join("p/model/fm/inverse.safetensors").exists(), "no inverse dynamics beside FM");
    let again = ok(&dir, &["pipeline", "-o", "p"]);
    assert_eq!(again.matches("(skipped)").count(), 6, "{again}");
    // Stage by stage (as the cluster runs them), the same expert and the same dataset: the
    // rollouts of each clip on their own, then joined.
    let (success, text) = flowmimic(&dir, &["pipeline", "-o", "q", "--only", "train:fm"]);
    assert!(!success && text.contains("q/data is not done yet: run the collect stage first"), "{text}");
    for stage in ["clips", "expert:walk_straight", "rollouts:walk_straight", "collect"] {
        ok(&dir, &["pipeline", "-o", "q", "--only", stage]);
    }
    let joined = ok(&dir, &["pipeline", "-o", "q", "--only", "collect"]);
    assert!(joined.contains("(skipped)"), "{joined}");
    for file in ["experts/walk_straight/policy.safetensors", "data/walk_straight.rollouts.safetensors"] {
        let (p, q) = (dir.join("p").join(file), dir.join("q").join(file));
        assert!(common::tensor_bytes(&p) == common::tensor_bytes(&q), "{file} differs stage by stage");
    }
    let stamp = |run: &str| std::fs::read_to_string(dir.join(run).join("data/stage.json")).unwrap();
    let key = |text: String| text.lines().find(|l| l.contains("\"key\"")).unwrap().to_string();
    assert_eq!(key(stamp("p")), key(stamp("q")));
    // Other clips into the same directory replace the clips it had.
    ok(&dir, &["motion", "generate", "--duration", "2", "--name", "short", "-o", "gen"]);
    ok(&dir, &["pipeline", "-o", "q", "--only", "clips", "--clip", "gen/short.clip.safetensors"]);
    let clips: Vec<_> = std::fs::read_dir(dir.join("q/clips")).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert!(clips.contains(&"short.clip.safetensors".into()) && clips.len() == 2, "{clips:?}"); // and stage.json
    // One policy over both clips and the FM model alone ([pipeline]): the plan names them, and
    // stage by stage the dataset is the one the whole pipeline collects.
    std::fs::write(dir.join("one.toml"), "[pipeline]\nexperts = \"one\"\nobjectives = [\"fm\"]\n").unwrap();
    let both = ["--clip", "gen/short.clip.safetensors", "p/clips/walk_straight.clip.safetensors"];
    let one = |out: &str, rest: &[&str]| ok(&dir, &[&["--config", "one.toml", "pipeline", "-o", out], rest].concat());
    one("r", &both);
    assert!(dir.join("r/experts/all/policy.safetensors").exists() && !dir.join("r/model/ddpm").exists());
    one("s", &[&["--only", "clips"], &both[..]].concat());
    let plan = one("s", &["--plan"]);
    assert!(plan.contains(r#""experts":["all"]"#) && plan.contains(r#"["short","all"]"#), "{plan}");
    assert!(plan.contains(r#""models":["fm"]"#), "{plan}");
    for stage in ["expert:all", "rollouts:short", "rollouts:walk_straight", "collect"] {
        one("s", &["--only", stage]);
    }
    for file in ["data/short.rollouts.safetensors", "data/walk_straight.rollouts.safetensors"] {
        assert!(common::tensor_bytes(&dir.join("r").join(file)) == common::tensor_bytes(&dir.join("s").join(file)));
    }
    let (success, text) = flowmimic(&dir, &["--config", "one.toml", "pipeline", "-o", "s", "--only", "train:ddpm"]);
    assert!(!success && text.contains("the models of this pipeline are [\"fm\"]"), "{text}");
    // The one policy started from another run's, trained one iteration more, and a model
    // directory's recommended settings (without its comments) for the FM model.
    let init = "init = \"r/experts/all\"\ninit_iterations = 1\nrecommended = \"pretrained/models/fm\"\n";
    std::fs::write(dir.join("init.toml"), format!("[pipeline]\nexperts = \"one\"\nobjectives = [\"fm\"]\n{init}"))
        .unwrap();
    let text = ok(&dir, &[&["--config", "init.toml", "pipeline", "-o", "i"], &both[..]].concat());
    assert!(text.contains("starting from the policy of") && text.contains("r/experts/all"), "{text}");
    let log = std::fs::read_to_string(dir.join("i/experts/all/log.csv")).unwrap();
    assert_eq!(log.lines().count(), 2, "one iteration more: {log}");
    let recommended = std::fs::read_to_string(dir.join("i/model/fm/recommended.toml")).unwrap();
    assert!(recommended.contains("[joystick]") && recommended.contains("adaptive = 1.5"), "{recommended}");
    assert!(!recommended.contains("m/s"), "the shipped model's measurements were copied: {recommended}");
    assert!(text.contains("w 50 (model)") || text.contains("| 50 |"), "not evaluated at its settings: {text}");
    // Other recommended settings: the same model, evaluated again at them.
    let walks = init.replace("models/fm\"", "models/fm-walks\"");
    std::fs::write(dir.join("init.toml"), format!("[pipeline]\nexperts = \"one\"\nobjectives = [\"fm\"]\n{walks}"))
        .unwrap();
    let text = ok(&dir, &[&["--config", "init.toml", "pipeline", "-o", "i"], &both[..]].concat());
    assert!(text.contains("== train fm: up to date") && text.contains("== evaluate ->"), "{text}");
    let recommended = std::fs::read_to_string(dir.join("i/model/fm/recommended.toml")).unwrap();
    assert!(recommended.contains("fm-walks") && recommended.contains("adaptive = 0"), "{recommended}");
    assert!(!recommended.contains("executor"), "fm-walks' executor suits its plans, not this model's: {recommended}");
    let report = std::fs::read_to_string(dir.join("i/eval/report.md")).unwrap();
    assert_eq!(report.matches("## Joystick tracking").count(), 1, "the report holds this evaluation only: {report}");
    // A layer that sets init_iterations = 0 (as configs/recipe-fm.toml over the cpu preset)
    // trains the policy from new weights, whatever init says.
    std::fs::write(dir.join("scratch.toml"), "[pipeline]\ninit_iterations = 0\n").unwrap();
    let scratch = |rest: &[&str]| {
        let layers = ["--config", "init.toml", "--config", "scratch.toml", "pipeline", "-o", "n"];
        ok(&dir, &[&layers[..], rest].concat())
    };
    scratch(&[&["--only", "clips"], &both[..]].concat());
    let text = scratch(&["--only", "expert:all"]);
    assert!(!text.contains("starting from the policy of"), "{text}");
    let log = std::fs::read_to_string(dir.join("n/experts/all/log.csv")).unwrap();
    assert!(log.lines().count() > 2, "the preset's iterations from new weights: {log}");
    std::fs::write(dir.join("bad.toml"), "[pipeline]\ninit_iterations = 2\n").unwrap();
    let (success, text) = flowmimic(&dir, &["--config", "bad.toml", "pipeline", "-o", "b"]);
    assert!(!success && text.contains("pipeline.init_iterations"), "{text}");
    // The walking corpus, when no clip is given.
    std::fs::write(dir.join("corpus.toml"), "[pipeline]\nclips = \"walking-corpus\"\n").unwrap();
    ok(&dir, &["--config", "corpus.toml", "pipeline", "-o", "c", "--only", "clips"]);
    for clip in ["wander_4", "walk_back", "02_01", "humanoid3d_walk"] {
        assert!(dir.join(format!("c/clips/{clip}.clip.safetensors")).exists(), "{clip}");
    }
    // The generated clips, captures left out; and those without the reaches.
    let generated = |source: &str| -> Vec<String> {
        std::fs::write(dir.join("generated.toml"), format!("[pipeline]\nclips = \"{source}\"\n")).unwrap();
        ok(&dir, &["--config", "generated.toml", "pipeline", "-o", source, "--only", "clips"]);
        let mut names: Vec<String> = std::fs::read_dir(dir.join(source).join("clips"))
            .unwrap()
            .filter_map(|e| e.unwrap().file_name().to_str()?.strip_suffix(".clip.safetensors").map(String::from))
            .collect();
        names.sort();
        names
    };
    let all = generated("generated");
    for clip in ["wander_4", "walk_back", "reach_4", "reach_stand", "transitions_2"] {
        assert!(all.iter().any(|g| g == clip), "{clip} not in {all:?}");
    }
    assert_eq!(all.len(), 12, "{all:?}");
    let walks = generated("generated-walks");
    let without_reaches: Vec<String> = all.iter().filter(|c| !c.starts_with("reach_")).cloned().collect();
    assert_eq!(walks, without_reaches);
    assert_eq!(walks.len(), 7, "{walks:?}");
    // Other model settings leave the stages before the model alone, and refuse to overwrite
    // the trained model.
    std::fs::write(dir.join("wider.toml"), "[model]\nd_model = 24\n").unwrap();
    let (success, text) = flowmimic(&dir, &["--config", "wider.toml", "pipeline", "-o", "p"]);
    assert!(!success && text.matches("(skipped)").count() == 3, "{text}");
    assert!(text.contains("'train fm'") && text.contains("another output directory"), "{text}");
    // So do other expert settings, whose dataset the model was not trained on.
    std::fs::write(dir.join("longer.toml"), "[track]\niterations = 3\n").unwrap();
    let (success, text) = flowmimic(&dir, &["--config", "longer.toml", "pipeline", "-o", "p"]);
    assert!(!success && text.contains("holds a model trained on other data or settings"), "{text}");
    // A damaged artifact stops the pipeline with the stage and the file.
    std::fs::write(dir.join("p/experts/walk_straight/policy.safetensors"), b"damaged").unwrap();
    std::fs::remove_file(dir.join("p/experts/walk_straight/stage.json")).unwrap();
    let (success, text) = flowmimic(&dir, &["pipeline", "-o", "p"]);
    assert!(!success && text.contains("expert 'walk_straight'") && text.contains("policy.safetensors"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

/// `flowmimic view` serves the page and the rollout; where Chromium is installed, a headless
/// browser loads it, steps the timeline to frame 10 and takes a screenshot.
fn viewer_serves_and_draws(dir: &Path, file: &str) {
    use std::io::{BufRead, Read, Write};
    let mut server =
        common::command(dir, &["view", file, "--port", "0"]).stdout(std::process::Stdio::piped()).spawn().unwrap();
    let mut line = String::new();
    std::io::BufReader::new(server.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let url = line.split_whitespace().nth(1).expect("the viewer prints its address").to_string();
    let host = url.trim_start_matches("http://").trim_end_matches('/').to_string();
    // An idle client (connected, saying nothing) does not stop others being served.
    let _idle = std::net::TcpStream::connect(&host).unwrap();
    let mut foreign = std::net::TcpStream::connect(&host).unwrap();
    write!(foreign, "GET /data.json HTTP/1.1\r\nHost: evil.example\r\nConnection: close\r\n\r\n").unwrap();
    let mut reply = String::new();
    foreign.read_to_string(&mut reply).unwrap();
    assert!(reply.starts_with("HTTP/1.1 403"), "a foreign Host header was answered: {reply:.100}");
    let mut stream = std::net::TcpStream::connect(&host).unwrap();
    write!(stream, "GET /data.json HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n").unwrap();
    let mut reply = String::new();
    stream.read_to_string(&mut reply).unwrap();
    assert!(
        reply.starts_with("HTTP/1.1 200") && reply.contains("\"bodies\"") && reply.contains("\"R_Hand\""),
        "{reply:.300}"
    );
    let shot = dir.join("viewer.png");
    let browser = ["chromium", "chromium-browser", "google-chrome"]
        .into_iter()
        .find(|b| Command::new(b).arg("--version").output().is_ok_and(|o| o.status.success()));
    match browser {
        Some(b) => {
            let out = Command::new(b)
                .args([
                    "--headless",
                    "--no-sandbox",
                    "--disable-gpu",
                    "--window-size=800,600",
                    "--virtual-time-budget=3000",
                ])
                .arg(format!("--screenshot={}", shot.display()))
                .arg(format!("{url}?frame=10"))
                .output()
                .unwrap();
            let png = std::fs::read(&shot).unwrap_or_default();
            assert!(png.len() > 20_000, "screenshot of {} bytes: {}", png.len(), String::from_utf8_lossy(&out.stderr));
        }
        None => eprintln!("no Chromium here: the viewer page was served but not drawn"),
    }
    server.kill().unwrap();
    server.wait().unwrap();
}

/// `make demo`'s command on the shipped guidance model: it walks forward, turns left, turns
/// right and walks backward, then touches a hand target, without falling (measured here: +0.87
/// m/s, +0.57 and -0.56 rad/s for +-0.6, -0.50 m/s for -0.5, the hand within 0.08 m), and writes
/// what the README shows. A model without inverse dynamics is told how to run it.
#[test]
fn the_demo_follows_its_joystick_schedule_and_touches_the_target() {
    let dir = workdir("demo");
    let models = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../pretrained/models"));
    let fm = models.join("fm").display().to_string();
    let text = ok(&dir, &["demo", "--model", &fm, "-o", "demo"]);
    assert_eq!(text.matches("no fall").count(), 2, "{text}");
    // Each segment's line: "commanded VX m/s forward at RATE rad/s: achieved VX m/s forward,
    // VY m/s left, RATE rad/s (from 1 s in)".
    let achieved: Vec<(f64, f64)> = text
        .lines()
        .filter_map(|l| l.split_once("achieved "))
        .map(|(_, rest)| {
            let numbers: Vec<f64> = rest.split_whitespace().filter_map(|w| w.parse().ok()).collect();
            (numbers[0], numbers[2])
        })
        .collect();
    assert_eq!(achieved.len(), 4, "{text}");
    let [(forward, _), (_, left), (_, right), (backward, _)] = achieved[..] else { unreachable!() };
    assert!(forward > 0.6 && left > 0.3 && right < -0.3 && backward < -0.3, "{achieved:?}\n{text}");
    let closest: f64 =
        text.split("closest hand-target distance ").nth(1).and_then(|r| r.split(' ').next()).unwrap().parse().unwrap();
    assert!(closest < 0.15, "{text}");
    for file in
        ["joystick.rollout.safetensors", "reach.rollout.safetensors", "joystick_heading.png", "reach_distance.svg"]
    {
        assert!(dir.join("demo").join(file).exists(), "demo/{file} missing");
    }
    let walk = models.join("fm-walk").display().to_string();
    let args = ["demo", "--model", &walk, "--inverse-dynamics", "0.2", "-o", "demo-walk"];
    let (success, text) = flowmimic(&dir, &args);
    assert!(!success && text.contains("no inverse.safetensors") && text.contains("--inverse-dynamics 0"), "{text}");
}

/// Obstacles from a file and from the command line are solid (MuJoCo's contacts, counted in the
/// outcome and kept in the rollout); bad ones are refused naming the file, the obstacle and the
/// problem; `eval forest` runs and reports every trial.
#[test]
fn obstacles_come_from_files_and_the_command_line() {
    let dir = workdir("obstacles");
    let example = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/obstacles.toml");
    let example = example.to_str().unwrap();
    let args = ["run", "--task", "waypoint", "--goal", "8,0", "--obstacles", example, "--seconds", "3"];
    let text = ok(&dir, &[&args[..], &["-o", "r.rollout.safetensors"]].concat());
    assert!(text.contains("obstacles: touched in 0 of 1"), "{text}");
    let again = ok(&dir, &["eval", "outcome", "r.rollout.safetensors"]);
    assert!(again.contains("obstacles: touched in 0 of 1"), "the rollout keeps its obstacles:\n{again}");
    // A post just ahead of a humanoid that walks on, unguided: it walks into it.
    let text = ok(&dir, &["run", "--obstacles", "0.6,0,0.3;", "--seconds", "2"]);
    assert!(text.contains("obstacles: touched in 1 of 1"), "{text}");

    let refused = |args: &[&str], words: &[&str]| {
        let (success, text) = flowmimic(&dir, args);
        assert!(!success, "{args:?} succeeded:\n{text}");
        words.iter().for_each(|w| assert!(text.contains(w), "{args:?}: no '{w}' in:\n{text}"));
    };
    std::fs::write(dir.join("typo.toml"), "[[obstacle]]\ntype = \"cylinder\"\nradius = 0.3\nat = [1, 2]\ncolour = 1\n")
        .unwrap();
    refused(&["run", "--obstacles", "typo.toml"], &["typo.toml", "obstacle 1", "unknown key", "colour"]);
    std::fs::write(
        dir.join("cone.json"),
        r#"[{"type": "cylinder", "radius": 0.3, "at": [1, 2]}, {"type": "cone", "at": [1, 1]}]"#,
    )
    .unwrap();
    refused(&["run", "--obstacles", "cone.json"], &["cone.json", "obstacle 2", "cone"]);
    std::fs::write(
        dir.join("both.toml"),
        "[[obstacle]]\ntype = \"cylinder\"\nradius = 0.3\nhalf = [1, 1]\nat = [1, 2]\n",
    )
    .unwrap();
    refused(&["run", "--obstacles", "both.toml"], &["both.toml", "obstacle 1", "half", "cylinder"]);
    refused(&["run", "--obstacles", "1,2"], &["expected 3 numbers"]);
    refused(&["run", "--obstacles", "1,2,0.3;4,0,-1"], &["obstacle 2", "size -1"]);
    refused(&["run", "--obstacles", "missing.toml"], &["missing.toml"]);

    let text = ok(&dir, &["eval", "forest", "--quick", "--trials", "2", "-o", "forest"]);
    assert!(text.contains("steps touching") && text.contains("| fm |"), "{text}");
}
