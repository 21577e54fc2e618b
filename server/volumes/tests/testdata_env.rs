//! `shared_data_dir` honours `VOXLIGHT_DATA` (own test binary: it changes the environment).

use voxlight_volumes::testdata::{DATA_ENV, shared_data_dir};

#[test]
fn env_override_wins_and_is_validated() {
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("README.md"), b"data").unwrap();
    // SAFETY: this binary has a single test, so no other thread reads the environment.
    unsafe { std::env::set_var(DATA_ENV, tmp.path()) };
    assert_eq!(shared_data_dir().as_deref(), Some(tmp.path()));
    let missing = tmp.path().join("nope");
    // SAFETY: as above.
    unsafe { std::env::set_var(DATA_ENV, &missing) };
    assert_eq!(
        shared_data_dir(),
        None,
        "a wrong VOXLIGHT_DATA must not fall back silently"
    );
    // SAFETY: as above.
    unsafe { std::env::remove_var(DATA_ENV) };
    let found = shared_data_dir().expect("../shared/data beside the repository");
    assert!(found.join("ct-chest-lidc").is_dir(), "{}", found.display());
}
