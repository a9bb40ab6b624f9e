//! Mesh files named by rig, URDF and cell files (STL, binary or ASCII, and Wavefront OBJ),
//! read for their vertices only: the checker uses the convex hull of a mesh, never its
//! faces (no convex decomposition; docs/cell.md). Owns the reading; the hull is built by
//! the checker.

use super::{ConfigError, Verbatim};
use glam::DVec3;
use std::path::{Path, PathBuf};

/// The largest mesh file read (64 MiB): a collision mesh of a robot link is well under a
/// megabyte; anything near this is a visual scan, not collision geometry.
pub const MAX_MESH_BYTES: u64 = 64 << 20;

/// The vertices of the mesh `name` (at `key` in `file`), a path relative to `file`'s
/// directory, or absolute; a `package://` or `file://` URI as URDF writes them is read as
/// the path after the scheme (a package's name is its directory beside the file).
pub fn read_hull_points(file: &Path, key: &str, name: &str) -> Result<Vec<DVec3>, ConfigError> {
    let path = resolve(file, name);
    let invalid = |reason: String| ConfigError::invalid(file, key, name, &reason);
    let meta = std::fs::metadata(&path)
        .map_err(|e| invalid(format!("cannot read {}: {e}", path.display())))?;
    if meta.len() > MAX_MESH_BYTES {
        return Err(ConfigError::invalid(
            file,
            key,
            Verbatim(format!("{} bytes", meta.len())),
            &format!("a mesh file is at most {MAX_MESH_BYTES} bytes"),
        ));
    }
    let extension = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let points = match extension.as_deref() {
        Some("stl") => read_stl(&path),
        Some("obj") => read_obj(&path),
        _ => Err(MeshReadError::Format),
    }
    .map_err(|reason| invalid(format!("{}: {reason}", path.display())))?;
    if points.iter().any(|p| !p.is_finite()) {
        return Err(invalid(format!(
            "{}: a vertex is not a finite number",
            path.display()
        )));
    }
    Ok(points)
}

/// Where `name` points, relative to `file`'s directory.
fn resolve(file: &Path, name: &str) -> PathBuf {
    let bare = name
        .strip_prefix("package://")
        .or_else(|| name.strip_prefix("file://"))
        .unwrap_or(name);
    let dir = file.parent().unwrap_or(Path::new("."));
    dir.join(bare)
}

/// Why a mesh file gave no vertices (said after its path).
#[derive(Debug, thiserror::Error)]
enum MeshReadError {
    #[error("only STL (.stl) and OBJ (.obj) meshes are read")]
    Format,
    #[error("{0}")]
    Stl(#[from] std::io::Error),
    #[error("{0}")]
    Obj(#[from] tobj::LoadError),
}

fn read_stl(path: &Path) -> Result<Vec<DVec3>, MeshReadError> {
    let mut reader = std::fs::File::open(path)?;
    let mesh = stl_io::read_stl(&mut reader)?;
    Ok(mesh
        .vertices
        .iter()
        .map(|v| DVec3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])))
        .collect())
}

fn read_obj(path: &Path) -> Result<Vec<DVec3>, MeshReadError> {
    let options = tobj::LoadOptions::default();
    let (models, _materials) = tobj::load_obj(path, &options)?;
    Ok(models
        .iter()
        .flat_map(|model| model.mesh.positions.chunks_exact(3))
        .map(|p| DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
        .collect())
}
