//! Where the real data for tests and benchmarks lives (7-Scenes redkitchen frames, LPIPS weights,
//! reference trajectories). It is never copied into the repository: it is read through a path
//! setting, the environment variable `MAC_EGO3D_SHARED`, defaulting to `../shared` next to the
//! repository root.
//!
//! Tests that need it are named `real_data_*`. They fail with a clear message when the data is
//! missing; `scripts/test.sh` skips them (and says so) on a machine without the data, except under
//! CI (`CI=true`), where missing data is a failure.

use std::path::{Path, PathBuf};

/// Environment variable that points at the shared data folder.
pub const SHARED_ENV: &str = "MAC_EGO3D_SHARED";

/// The shared data folder: `$MAC_EGO3D_SHARED`, or `../shared` beside the workspace root.
pub fn shared_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os(SHARED_ENV) {
        return PathBuf::from(dir);
    }
    // This crate sits one level below the workspace root; resolve the `..`s for readable messages.
    let default = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("..")
        .join("shared");
    default.canonicalize().unwrap_or(default)
}

/// Path of `relative` inside the shared folder, or a panic that says what is missing and how to
/// point the tests at it. Only for tests and benchmarks.
pub fn require(relative: &str) -> PathBuf {
    let path = shared_dir().join(relative);
    if !path.exists() {
        panic!(
            "real data missing: {} does not exist. Set {SHARED_ENV} to the folder that holds \
             datasets/, weights/ and reference/ (default ../shared beside the repository).",
            path.display()
        );
    }
    path
}
