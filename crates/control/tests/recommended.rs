//! The shipped models' recommended settings parse and hold sensible values, and a bad file is
//! refused with its name and the setting.

use flowmimic_control::Recommended;
use std::path::Path;

#[test]
fn every_shipped_models_recommended_settings_load() {
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../pretrained/models");
    let mut loaded = 0;
    for entry in std::fs::read_dir(&models).unwrap() {
        let dir = entry.unwrap().path();
        if !dir.join(flowmimic_control::recommended::FILE).exists() {
            continue;
        }
        let r = Recommended::load(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        assert!(r.walk.nfe.is_some(), "{}: no walking NFE", dir.display());
        loaded += 1;
    }
    assert!(loaded >= 6, "{loaded} models with recommended settings");
    // The default guidance model is driven as its joystick bar was measured.
    let fm = Recommended::load(&models.join("fm")).unwrap();
    assert_eq!((fm.joystick.nfe, fm.joystick.guidance_scale, fm.joystick.adaptive), (Some(2), Some(50.0), Some(1.5)));
    assert_eq!(fm.joystick.inverse_dynamics, Some(0.2));
    assert_eq!(fm.reach.approach, Some(true));
}

#[test]
fn a_bad_recommended_file_is_refused_with_its_name() {
    let dir = std::env::temp_dir().join(format!("flowmimic-recommended-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    assert_eq!(Recommended::load(&dir).unwrap(), Recommended::default(), "no file: no settings");
    let file = dir.join("recommended.toml");
    for (text, word) in [
        ("[joystick]\ninverse_dynamics = 1.5\n", "inverse_dynamics"),
        ("[reach]\nnfe = 0\n", "nfe"),
        ("[joystick]\nguidance_interval = [3, 1]\n", "guidance_interval"),
        ("[joystik]\nnfe = 2\n", "joystik"),
        ("[walk]\nadaptive = -1.0\n", "adaptive"),
        ("[play]\nguidance_scale = -30.0\n", "guidance_scale"),
        ("[joystick]\nacceleration = -1.0\n", "[joystick] acceleration = -1"),
        ("[walk]\nstart_actions = \"expert\"\n", "inverse-dynamics"),
    ] {
        std::fs::write(&file, text).unwrap();
        let err = Recommended::load(&dir).unwrap_err().to_string();
        assert!(err.contains("recommended.toml") && err.contains(word), "{text}: {err}");
    }
    std::fs::write(&file, "[joystick]\nadaptive = 0.0\n").unwrap();
    assert_eq!(Recommended::load(&dir).unwrap().joystick.adaptive, Some(0.0), "0: the fixed scale");
    std::fs::write(&file, "[walk]\nstart_actions = \"inverse-dynamics\"\n").unwrap();
    let walk = Recommended::load(&dir).unwrap().walk;
    assert_eq!(walk.start_actions, Some(flowmimic_control::StartActions::InverseDynamics));
    // An executor is named from the model directory, and must be there.
    std::fs::write(&file, "[joystick]\nexecutor = \"../nowhere\"\n").unwrap();
    let err = Recommended::load(&dir).unwrap_err().to_string();
    assert!(err.contains("[joystick] executor") && err.contains("nowhere"), "{err}");
    std::fs::create_dir_all(dir.join("runs/executor")).unwrap();
    std::fs::write(&file, "[joystick]\nexecutor = \"runs/./executor/../executor\"\nexecutor_residual = 0.25\n")
        .unwrap();
    let joystick = Recommended::load(&dir).unwrap().joystick;
    assert_eq!(joystick.executor, Some(dir.join("runs/executor")), "joined to the model directory, tidied");
    assert_eq!(joystick.control(flowmimic_model::Gradient::ThroughNetwork, 1.0).unwrap().executor_residual, 0.25);
    std::fs::write(&file, "[walk]\nexecutor_residual = 2.0\n").unwrap();
    let err = Recommended::load(&dir).unwrap_err().to_string();
    assert!(err.contains("[walk] executor_residual = 2"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}
