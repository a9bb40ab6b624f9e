//! The configuration files shipped inside the binary (`config/*.toml`, by `include_str!`),
//! so that an installed `rigbridge` runs its defaults from any directory, and the one reader
//! every loader of configuration text goes through: a path under [`PREFIX`] names a shipped
//! file, any other path a file on disk. Owns no file format (the loaders parse what it
//! returns) and never writes anywhere but the directory `dump` is given.

use super::ConfigError;
use std::borrow::Cow;
use std::path::{Component, Path, PathBuf};

/// The directory shipped files live in: `embedded:/irb120.toml` is the built-in IRB 120.
/// A name no file system path starts with by accident, and shown as is in messages, so a
/// user sees which settings a run used and can name them on the command line too.
pub const PREFIX: &str = "embedded:";

/// One file shipped inside the binary.
#[derive(Debug, Clone, Copy)]
pub struct ShippedFile {
    /// Its name, the same as in the repository's `config/`.
    pub name: &'static str,
    pub text: &'static str,
}

macro_rules! shipped {
    ($($name:literal),* $(,)?) => {
        [$(ShippedFile { name: $name, text: include_str!(concat!("../../config/", $name)) }),*]
    };
}

/// Every shipped file: the IRB 120 rig and the demo run settings, and the files they name
/// (rigs, the sloth, the painter's room, the forest, the cells), so relative names inside them resolve
/// among the shipped files as they do on disk.
pub const FILES: [ShippedFile; 11] = shipped!(
    "rigbridge.toml",
    "irb120.toml",
    "gait-run.toml",
    "sloth.toml",
    "forest.toml",
    "paint-run.toml",
    "painter.toml",
    "paint.toml",
    "cell-floor.toml",
    "cell-star.toml",
    "cell-painter.toml",
);

/// The path of the shipped file `name` (it may not exist: [`read`] says so).
pub fn path(name: &str) -> PathBuf {
    Path::new(PREFIX).join(name)
}

/// The default run settings: the IRB 120 tracing its star against the loopback twin.
pub const DEFAULT_RUN_SETTINGS: &str = "embedded:/rigbridge.toml";
/// The default rig of the batch tools.
pub const DEFAULT_RIG: &str = "embedded:/irb120.toml";

/// True when `path` lies in the shipped directory (or is it).
pub fn is_shipped(path: &Path) -> bool {
    path.components().next() == Some(Component::Normal(PREFIX.as_ref()))
}

/// The shipped file `path` names, when `path` is in the shipped directory: one plain name
/// after the prefix (`.` components allowed, nothing else).
pub fn find(path: &Path) -> Option<&'static ShippedFile> {
    let mut components = path.components().filter(|c| *c != Component::CurDir);
    if components.next() != Some(Component::Normal(PREFIX.as_ref())) {
        return None;
    }
    let name = match (components.next(), components.next()) {
        (Some(Component::Normal(name)), None) => name.to_str()?,
        _ => return None,
    };
    FILES.iter().find(|file| file.name == name)
}

/// The names of the shipped files, for messages.
pub fn names() -> String {
    FILES.iter().map(|f| f.name).collect::<Vec<_>>().join(", ")
}

/// The text of the configuration file at `path`: a shipped file or one on disk. A missing
/// file's error says where it looked (the absolute path) or which files are built in.
pub fn read(path: &Path) -> Result<Cow<'static, str>, ConfigError> {
    if is_shipped(path) {
        return find(path)
            .map(|file| Cow::Borrowed(file.text))
            .ok_or_else(|| ConfigError::NotShipped {
                file: path.to_path_buf(),
                names: names(),
            });
    }
    std::fs::read_to_string(path)
        .map(Cow::Owned)
        .map_err(|source| ConfigError::Io {
            file: path.to_path_buf(),
            looked: looked_for(path),
            source,
        })
}

/// Where a relative `path` is looked for: against the working directory, shown absolute so
/// that a user who ran from elsewhere sees the directory that was searched.
fn looked_for(path: &Path) -> String {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut shown = absolute.display().to_string();
    if let Some(name) = path.file_name().and_then(|n| n.to_str())
        && FILES.iter().any(|f| f.name == name)
    {
        shown.push_str(&format!(
            "; the built-in one is {}",
            self::path(name).display()
        ));
    }
    shown
}

/// What `dump` did with one file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Dumped {
    Written(PathBuf),
    /// Already there, left alone (no `force`).
    Kept(PathBuf),
}

/// Why the shipped files could not be written out.
#[derive(Debug, thiserror::Error)]
pub enum DumpError {
    #[error("cannot create the directory {dir}")]
    CreateDir {
        dir: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {file}")]
    Write {
        file: PathBuf,
        source: std::io::Error,
    },
}

/// Writes every shipped file into `dir` (created if needed) for editing. An existing file is
/// kept unless `force`: a user's edits are never overwritten by accident.
pub fn dump(dir: &Path, force: bool) -> Result<Vec<Dumped>, DumpError> {
    std::fs::create_dir_all(dir).map_err(|source| DumpError::CreateDir {
        dir: dir.to_path_buf(),
        source,
    })?;
    let mut done = Vec::with_capacity(FILES.len());
    for file in &FILES {
        let target = dir.join(file.name);
        if !force && std::fs::symlink_metadata(&target).is_ok() {
            done.push(Dumped::Kept(target));
            continue;
        }
        std::fs::write(&target, file.text).map_err(|source| DumpError::Write {
            file: target.clone(),
            source,
        })?;
        done.push(Dumped::Written(target));
    }
    Ok(done)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_names_resolve_and_others_do_not() {
        let irb = find(Path::new(DEFAULT_RIG)).expect("the IRB 120 is shipped");
        assert!(irb.text.contains("joint_6"));
        let joined = Path::new(DEFAULT_RUN_SETTINGS)
            .parent()
            .expect("a directory")
            .join("irb120.toml");
        assert!(find(&joined).is_some(), "{}", joined.display());
        for other in [
            "irb120.toml",
            "embedded:/nope.toml",
            "embedded:/../irb120.toml",
            "embedded:/a/irb120.toml",
        ] {
            assert!(find(Path::new(other)).is_none(), "{other}");
        }
        let missing = read(Path::new("embedded:/nope.toml")).unwrap_err();
        assert!(missing.to_string().contains("irb120.toml"), "{missing}");
    }

    #[test]
    fn a_missing_file_says_where_it_looked() {
        let error = read(Path::new("no/such/rigbridge.toml")).unwrap_err();
        let shown = error.to_string();
        let cwd = std::env::current_dir().expect("a working directory");
        assert!(
            shown.contains(&cwd.join("no/such/rigbridge.toml").display().to_string()),
            "{shown}"
        );
        assert!(shown.contains(DEFAULT_RUN_SETTINGS), "{shown}");
    }
}
