//! Stored trials are never lost: a CSV written with other columns (an older version of an
//! experiment) is moved aside, not overwritten.

use flowmimic_eval::sweep::Store;

#[test]
fn trials_stored_with_other_columns_are_moved_aside() {
    let dir = std::env::temp_dir().join(format!("flowmimic-store-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("joystick.csv");
    let old = "model,objective,horizon,nfe,scale,gradient,execute,seed,trial,velocity_rmse,fell\nfm@1,fm,16,2,0,through-network,1,0,0,0.7,0\n";
    std::fs::write(&path, old).unwrap();
    // A second old file is not overwritten either.
    std::fs::write(dir.join("joystick.old.csv"), "older").unwrap();
    Store::open(path.clone(), &["velocity_rmse", "forward_rmse", "fell"]).unwrap();
    assert!(!path.exists(), "moved aside");
    assert_eq!(std::fs::read_to_string(dir.join("joystick.old2.csv")).unwrap(), old);
    assert_eq!(std::fs::read_to_string(dir.join("joystick.old.csv")).unwrap(), "older");
    // A file with this version's columns stays where it is.
    let same = "model,objective,horizon,nfe,scale,gradient,execute,seed,trial,velocity_rmse,fell\n";
    std::fs::write(&path, same).unwrap();
    Store::open(path.clone(), &["velocity_rmse", "fell"]).unwrap();
    assert_eq!(std::fs::read_to_string(&path).unwrap(), same);
    std::fs::remove_dir_all(&dir).unwrap();
}
