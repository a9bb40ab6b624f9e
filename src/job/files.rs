//! Files a job names (a paint settings file, a forest, a trajectory CSV): always relative to
//! the directory of the config that holds the job, never outside it. Owns only that rule;
//! reading a file is its kind's business, and no refusal here quotes a file's content.

use super::JobInvalid;
use std::path::{Component, Path, PathBuf};

/// `name` (the value of `key`) inside `base_dir`: a relative path without `..`, naming an
/// existing file that (after following links) still lies inside `base_dir`. A missing file's
/// refusal says where it looked.
pub fn resolve_file(base_dir: &Path, key: &str, name: &Path) -> Result<PathBuf, JobInvalid> {
    let shown = name.display().to_string();
    let plain = name
        .components()
        .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    if name.as_os_str().is_empty() || !plain {
        return Err(JobInvalid::new(
            key,
            shown,
            "must be a file name relative to the config's directory, without `..`",
        ));
    }
    let path = base_dir.join(name);
    if crate::rig::shipped::is_shipped(base_dir) {
        // The config is built in: so are the files it names, and nothing on disk is reachable.
        return match crate::rig::shipped::find(&path) {
            Some(_) => Ok(path),
            None => Err(JobInvalid::new(
                key,
                shown,
                format!(
                    "no such built-in file {} (built in: {})",
                    path.display(),
                    crate::rig::shipped::names()
                ),
            )),
        };
    }
    let (Ok(real), Ok(real_base)) = (path.canonicalize(), base_dir.canonicalize()) else {
        return Err(JobInvalid::new(
            key,
            shown,
            format!("no such file: looked for {}", path.display()),
        ));
    };
    if !real.starts_with(&real_base) || !real.is_file() {
        return Err(JobInvalid::new(
            key,
            shown,
            format!(
                "must be a file inside the config's directory {}",
                base_dir.display()
            ),
        ));
    }
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_files_inside_the_directory_resolve() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        assert!(resolve_file(&dir, "k", Path::new("paint.toml")).is_ok());
        for bad in ["/etc/passwd", "../Cargo.toml", "", "nope.toml", "."] {
            let refused = resolve_file(&dir, "k", Path::new(bad));
            assert!(refused.is_err(), "{bad} must be refused");
        }
        let missing = resolve_file(&dir, "k", Path::new("nope.toml")).unwrap_err();
        assert!(missing.reason.contains("config/nope.toml"), "{missing}");
    }
}
