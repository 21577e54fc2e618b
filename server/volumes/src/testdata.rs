//! Locating the shared real-data folder (`../shared/data`) for tests in any crate.

use std::path::{Path, PathBuf};

/// Environment variable that overrides where the shared test data lives.
pub const DATA_ENV: &str = "VOXLIGHT_DATA";

fn candidates() -> Vec<PathBuf> {
    let mut starts = Vec::new();
    if let Some(m) = option_env!("CARGO_MANIFEST_DIR") {
        starts.push(PathBuf::from(m));
    }
    if let Ok(m) = std::env::var("CARGO_MANIFEST_DIR") {
        starts.push(PathBuf::from(m));
    }
    if let Ok(c) = std::env::current_dir() {
        starts.push(c);
    }
    let mut out = Vec::new();
    for s in starts {
        for anc in s.ancestors() {
            let c = anc.join("shared").join("data");
            if !out.contains(&c) {
                out.push(c);
            }
        }
    }
    out
}

fn is_data_dir(p: &Path) -> bool {
    p.join("README.md").is_file()
}

/// The shared test-data folder: `$VOXLIGHT_DATA` if set, else the first `shared/data` found in
/// an ancestor of the crate or current directory (the repo's sibling `../shared/data`).
pub fn shared_data_dir() -> Option<PathBuf> {
    if let Some(v) = std::env::var_os(DATA_ENV) {
        let p = PathBuf::from(v);
        return is_data_dir(&p).then_some(p);
    }
    candidates().into_iter().find(|p| is_data_dir(p))
}

/// Like [`shared_data_dir`] but panics with a message naming every place searched. For tests
/// only: a test that needs the data must fail loudly, never pass silently.
pub fn require_shared_data_dir() -> PathBuf {
    match shared_data_dir() {
        Some(p) => p,
        None => {
            let looked: Vec<String> = candidates()
                .iter()
                .map(|p| p.display().to_string())
                .collect();
            panic!(
                "shared test data not found. {DATA_ENV}={:?}; looked in: {}. Set {DATA_ENV} to the \
                 folder holding the test volumes (the one with README.md, ct-chest-lidc/, vti/, ...).",
                std::env::var_os(DATA_ENV),
                looked.join(", ")
            )
        }
    }
}
