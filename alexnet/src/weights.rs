//! Where the pretrained AlexNet weights (`alexnet.npz`: the LPIPS v0.1 layers, also the
//! place-recognition descriptor's network) are found when no option or config names them.
//!
//! One place decides it for every process and command ([`default_alexnet_weights`]):
//! 1. `$MAC_EGO3D_WEIGHTS`, the path of an `alexnet.npz`, when set (set to a missing path or to
//!    the empty string, it turns the weights off: the classical descriptor and no LPIPS);
//! 2. the per-user cache, `$XDG_CACHE_HOME/mac-ego3d/weights/lpips/alexnet.npz`, by default
//!    `~/.cache/mac-ego3d/weights/lpips/alexnet.npz`, which `scripts/setup.sh` fills with
//!    `scripts/get_lpips_weights.sh` (or from the shared data folder when the download fails).
//!
//! An explicit option (`--descriptor-weights`, `--lpips-weights`, `--weights`) or config key
//! (`consensus.descriptor_weights`) always wins over this default. Without weights, commands fall
//! back (the classical thumbnail descriptor, no LPIPS) and say so once in their log.
//! `scripts/setup.sh` resolves the same path in shell; keep the two in step.

use std::ffi::OsStr;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Once;

/// Environment variable naming the `alexnet.npz` to use instead of the cache.
pub const WEIGHTS_ENV: &str = "MAC_EGO3D_WEIGHTS";
/// The weights file inside the cache folder.
pub const CACHE_RELATIVE: &str = "mac-ego3d/weights/lpips/alexnet.npz";
/// The command that fetches the weights (run from the repository root).
pub const FETCH_COMMAND: &str = "scripts/get_lpips_weights.sh";

/// Why no default weights were found: the path looked for (if any) and where it came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MissingWeights {
    /// The file looked for; `None` when there was nowhere to look (no cache folder, empty env).
    pub looked_for: Option<PathBuf>,
    /// Where that path came from, for the message.
    pub source: WeightsSource,
}

/// Where a default weights path comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightsSource {
    /// `$MAC_EGO3D_WEIGHTS`.
    Env,
    /// The per-user cache.
    Cache,
}

impl fmt::Display for MissingWeights {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (&self.looked_for, self.source) {
            (Some(path), WeightsSource::Env) => write!(
                f,
                "no AlexNet weights at {} (${WEIGHTS_ENV}); fetch them with: \
                 {FETCH_COMMAND} {}",
                path.display(),
                path.display()
            ),
            (None, WeightsSource::Env) => write!(f, "${WEIGHTS_ENV} is empty: no AlexNet weights"),
            (Some(path), WeightsSource::Cache) => write!(
                f,
                "no AlexNet weights at {} (the cache; ${WEIGHTS_ENV} unset); fetch them with: \
                 {FETCH_COMMAND} {} (scripts/setup.sh does it)",
                path.display(),
                path.display()
            ),
            (None, WeightsSource::Cache) => write!(
                f,
                "no AlexNet weights: neither ${WEIGHTS_ENV} nor a cache folder \
                 ($XDG_CACHE_HOME or $HOME) is set"
            ),
        }
    }
}

impl std::error::Error for MissingWeights {}

/// The cache file for a cache root (`$XDG_CACHE_HOME`, else `$HOME/.cache`); `None` when neither
/// is set (to an absolute path, as the XDG base-directory rules require).
pub fn cache_path_in(xdg_cache_home: Option<&OsStr>, home: Option<&OsStr>) -> Option<PathBuf> {
    let absolute =
        |value: Option<&OsStr>| value.map(PathBuf::from).filter(|path| path.is_absolute());
    let root = absolute(xdg_cache_home).or_else(|| absolute(home).map(|h| h.join(".cache")))?;
    Some(root.join(CACHE_RELATIVE))
}

/// The cache file of this process's environment (see [`cache_path_in`]).
pub fn cache_path() -> Option<PathBuf> {
    cache_path_in(
        std::env::var_os("XDG_CACHE_HOME").as_deref(),
        std::env::var_os("HOME").as_deref(),
    )
}

/// The resolution order, without reading the environment: `env` (the value of
/// `$MAC_EGO3D_WEIGHTS`, when set) decides alone; otherwise `cache` when that file exists.
pub fn resolve(env: Option<&OsStr>, cache: Option<&Path>) -> Result<PathBuf, MissingWeights> {
    let (looked_for, source) = match env {
        Some(value) if value.is_empty() => (None, WeightsSource::Env),
        Some(value) => (Some(PathBuf::from(value)), WeightsSource::Env),
        None => (cache.map(Path::to_path_buf), WeightsSource::Cache),
    };
    match looked_for {
        Some(path) if path.is_file() => Ok(path),
        looked_for => Err(MissingWeights { looked_for, source }),
    }
}

/// The default weights of this process's environment, or why there are none.
pub fn resolve_default() -> Result<PathBuf, MissingWeights> {
    resolve(
        std::env::var_os(WEIGHTS_ENV).as_deref(),
        cache_path().as_deref(),
    )
}

/// The default AlexNet weights (`$MAC_EGO3D_WEIGHTS`, else the cache), for every option and
/// config key left unset. Without them it logs one warning per process, naming the path looked
/// for and the command that fetches it (an info line when `$MAC_EGO3D_WEIGHTS` is empty: the
/// weights were turned off on purpose), and returns `None` (callers fall back).
pub fn default_alexnet_weights() -> Option<PathBuf> {
    static LOGGED: Once = Once::new();
    match resolve_default() {
        Ok(path) => Some(path),
        Err(missing) => {
            LOGGED.call_once(|| {
                const FALLBACK: &str = "Falling back: the classical thumbnail descriptor for \
                                        place recognition, no LPIPS figures";
                if missing.looked_for.is_none() && missing.source == WeightsSource::Env {
                    tracing::info!("{missing}. {FALLBACK}");
                } else {
                    tracing::warn!("{missing}. {FALLBACK}");
                }
            });
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn touch(path: &Path) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, b"npz").unwrap();
    }

    #[test]
    fn env_var_wins_over_the_cache_and_the_cache_is_the_default() {
        let dir = tempfile::tempdir().unwrap();
        let cache = cache_path_in(Some(dir.path().join("xdg").as_os_str()), None).unwrap();
        assert_eq!(cache, dir.path().join("xdg").join(CACHE_RELATIVE));
        let from_env = dir.path().join("elsewhere/alexnet.npz");
        touch(&cache);
        touch(&from_env);

        assert_eq!(
            resolve(Some(from_env.as_os_str()), Some(&cache)),
            Ok(from_env)
        );
        assert_eq!(resolve(None, Some(&cache)), Ok(cache));
    }

    #[test]
    fn missing_weights_give_none_with_the_path_and_the_fetch_command() {
        let dir = tempfile::tempdir().unwrap();
        let cache = dir.path().join("cache").join(CACHE_RELATIVE);

        let missing = resolve(None, Some(&cache)).unwrap_err();
        assert_eq!(missing.looked_for.as_deref(), Some(cache.as_path()));
        assert_eq!(missing.source, WeightsSource::Cache);
        let message = missing.to_string();
        assert!(message.contains(&cache.display().to_string()), "{message}");
        assert!(message.contains(FETCH_COMMAND), "{message}");

        // An env var naming a missing file turns the weights off even when the cache has them.
        touch(&cache);
        let absent = dir.path().join("absent.npz");
        let missing = resolve(Some(absent.as_os_str()), Some(&cache)).unwrap_err();
        assert_eq!(missing.looked_for, Some(absent.clone()));
        assert_eq!(missing.source, WeightsSource::Env);
        assert!(missing.to_string().contains(WEIGHTS_ENV));
        let empty = resolve(Some(OsStr::new("")), Some(&cache)).unwrap_err();
        assert_eq!(empty.looked_for, None);
        // A folder is not a weights file.
        assert!(resolve(Some(dir.path().as_os_str()), None).is_err());
        assert!(resolve(None, None).is_err());
    }

    #[test]
    fn cache_root_follows_xdg_then_home() {
        let home = OsStr::new("/home/u");
        assert_eq!(
            cache_path_in(None, Some(home)),
            Some(PathBuf::from("/home/u/.cache").join(CACHE_RELATIVE))
        );
        assert_eq!(
            cache_path_in(Some(OsStr::new("/x")), Some(home)),
            Some(PathBuf::from("/x").join(CACHE_RELATIVE))
        );
        // Relative values are ignored, as the XDG base-directory rules say.
        assert_eq!(
            cache_path_in(Some(OsStr::new("rel")), Some(home)),
            Some(PathBuf::from("/home/u/.cache").join(CACHE_RELATIVE))
        );
        assert_eq!(cache_path_in(None, None), None);
    }
}
