//! Collision geometry as plain data: convex solids, where they sit on a rig's links, and the
//! one TOML form of a solid that rig files and cell files share (validated, every error
//! naming the file, the key and the bad value). Owns no queries: the checker
//! (`crate::cell`) turns these shapes into its own.

use super::config::{Checker, origin_from_xyz_rpy};
use super::{ConfigError, Verbatim};
use glam::{DAffine3, DVec3};
use serde::Deserialize;
use std::path::Path;

pub(crate) use super::mesh::read_hull_points;

/// A convex solid in its own frame.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    Box {
        half_extents: DVec3,
    },
    /// Axis along its frame's z, centred on the origin.
    Cylinder {
        radius: f64,
        half_length: f64,
    },
    Sphere {
        radius: f64,
    },
    /// The points within `radius` of the segment `a`-`b`, in its frame.
    Capsule {
        a: DVec3,
        b: DVec3,
        radius: f64,
    },
    /// The solid `{ p : p . normal <= 0 }`, `normal` a unit vector (a floor, a wall).
    HalfSpace {
        normal: DVec3,
    },
    /// The convex hull of `points` (STL and OBJ meshes become the hull of their vertices).
    ConvexHull {
        points: Vec<DVec3>,
    },
}

impl Shape {
    /// The shape's kind as files write it (`box`, `cylinder`, ...).
    pub fn kind(&self) -> &'static str {
        match self {
            Shape::Box { .. } => "box",
            Shape::Cylinder { .. } => "cylinder",
            Shape::Sphere { .. } => "sphere",
            Shape::Capsule { .. } => "capsule",
            Shape::HalfSpace { .. } => "half_space",
            Shape::ConvexHull { .. } => "hull",
        }
    }

    /// The largest distance from the frame's origin to a point of the solid; `None` for
    /// an unbounded one (a half-space).
    pub fn bounding_radius(&self) -> Option<f64> {
        match self {
            Shape::Box { half_extents } => Some(half_extents.length()),
            Shape::Cylinder {
                radius,
                half_length,
            } => Some(radius.hypot(*half_length)),
            Shape::Sphere { radius } => Some(*radius),
            Shape::Capsule { a, b, radius } => Some(a.length().max(b.length()) + radius),
            Shape::HalfSpace { .. } => None,
            Shape::ConvexHull { points } => {
                Some(points.iter().map(|p| p.length()).fold(0.0, f64::max))
            }
        }
    }
}

/// One solid placed in its owner's frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Collision {
    /// The solid's frame in its owner's frame.
    pub origin: DAffine3,
    pub shape: Shape,
}

/// Collision geometry of one link of a rig: `frame` 0 is the rig's base (before joint 1),
/// `frame` k the frame after joint k (it moves with joint k), k = 1..=dof.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkBody {
    pub name: String,
    pub frame: usize,
    pub collisions: Vec<Collision>,
}

/// One solid as TOML writes it: `shape` names the kind, its own keys give the size (in
/// metres), `origin_xyz_m`/`origin_rpy_deg` place it. Meshes name a file (`mesh = "x.stl"`,
/// resolved by the caller) or list the points of their hull.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawSolid {
    pub(crate) name: Option<String>,
    pub(crate) shape: Option<String>,
    #[serde(default)]
    origin_xyz_m: [f64; 3],
    #[serde(default)]
    origin_rpy_deg: [f64; 3],
    size_m: Option<[f64; 3]>,
    radius_m: Option<f64>,
    length_m: Option<f64>,
    a_m: Option<[f64; 3]>,
    b_m: Option<[f64; 3]>,
    normal: Option<[f64; 3]>,
    points_m: Option<Vec<[f64; 3]>>,
    pub(crate) mesh: Option<String>,
}

/// The shape kinds a file may name, for messages.
const SHAPE_KINDS: &str = "box, cylinder, sphere, capsule, half_space, hull, mesh";

/// The size keys each kind takes; any other size key given is refused, so a typo (a
/// `radius_m` on a box) does not pass silently.
fn keys_of(kind: &str) -> &'static [&'static str] {
    match kind {
        "box" => &["size_m"],
        "cylinder" => &["radius_m", "length_m"],
        "sphere" => &["radius_m"],
        "capsule" => &["a_m", "b_m", "radius_m"],
        "half_space" => &["normal"],
        "hull" => &["points_m"],
        "mesh" => &["mesh"],
        _ => &[],
    }
}

/// Reads the meshes a solid names: the caller owns files (paths relative to its file).
pub(crate) type MeshReader<'a> = dyn Fn(&str, &str) -> Result<Vec<DVec3>, ConfigError> + 'a;

impl RawSolid {
    fn given(&self) -> [(&'static str, bool); 7] {
        [
            ("size_m", self.size_m.is_some()),
            ("radius_m", self.radius_m.is_some()),
            ("length_m", self.length_m.is_some()),
            ("a_m", self.a_m.is_some()),
            ("b_m", self.b_m.is_some()),
            ("normal", self.normal.is_some()),
            ("points_m", self.points_m.is_some()),
        ]
    }

    /// The solid as a [`Collision`]; `key` is where it sits in the file (`body[0].collision[1]`),
    /// so errors name `key.radius_m` and so on. `read_mesh` reads a `mesh` file's vertices.
    pub(crate) fn validate(
        &self,
        file: &Path,
        key: &str,
        read_mesh: &MeshReader<'_>,
    ) -> Result<Collision, ConfigError> {
        let checker = Checker { file, prefix: "" };
        let k = |field: &str| format!("{key}.{field}");
        let kind = self.shape.as_deref().ok_or_else(|| {
            ConfigError::invalid(
                file,
                &k("shape"),
                Verbatim("missing"),
                &format!("one of {SHAPE_KINDS}"),
            )
        })?;
        let wanted = keys_of(kind);
        if wanted.is_empty() {
            return Err(ConfigError::invalid(
                file,
                &k("shape"),
                kind,
                &format!("not a shape kind (one of {SHAPE_KINDS})"),
            ));
        }
        for (field, given) in self.given() {
            if given && !wanted.contains(&field) {
                return Err(ConfigError::invalid(
                    file,
                    &k(field),
                    Verbatim("(given)"),
                    &format!("a {kind} takes {} only", wanted.join(", ")),
                ));
            }
        }
        if self.mesh.is_some() && kind != "mesh" {
            return Err(ConfigError::invalid(
                file,
                &k("mesh"),
                Verbatim("(given)"),
                &format!("a {kind} takes {} only", wanted.join(", ")),
            ));
        }
        let positive = |field: &str, value: Option<f64>| -> Result<f64, ConfigError> {
            match value {
                Some(v) if v.is_finite() && v > 0.0 => Ok(v),
                Some(v) => Err(ConfigError::invalid(
                    file,
                    &k(field),
                    v,
                    "must be a positive number",
                )),
                None => Err(ConfigError::invalid(
                    file,
                    &k(field),
                    Verbatim("missing"),
                    &format!("required for a {kind}"),
                )),
            }
        };
        let vector = |field: &str, value: Option<[f64; 3]>| -> Result<DVec3, ConfigError> {
            match value {
                Some(v) => checker.finite3(k(field), v),
                None => Err(ConfigError::invalid(
                    file,
                    &k(field),
                    Verbatim("missing"),
                    &format!("required for a {kind}"),
                )),
            }
        };
        let shape = match kind {
            "box" => {
                let size = vector("size_m", self.size_m)?;
                if size.min_element() <= 0.0 {
                    return Err(ConfigError::invalid(
                        file,
                        &k("size_m"),
                        size.to_array(),
                        "every side must be positive",
                    ));
                }
                Shape::Box {
                    half_extents: size / 2.0,
                }
            }
            "cylinder" => Shape::Cylinder {
                radius: positive("radius_m", self.radius_m)?,
                half_length: positive("length_m", self.length_m)? / 2.0,
            },
            "sphere" => Shape::Sphere {
                radius: positive("radius_m", self.radius_m)?,
            },
            "capsule" => Shape::Capsule {
                a: vector("a_m", self.a_m)?,
                b: vector("b_m", self.b_m)?,
                radius: positive("radius_m", self.radius_m)?,
            },
            "half_space" => {
                let normal = vector("normal", self.normal)?;
                if normal.length() < 1e-9 {
                    return Err(ConfigError::invalid(
                        file,
                        &k("normal"),
                        normal.to_array(),
                        "must not be the zero vector",
                    ));
                }
                Shape::HalfSpace {
                    normal: normal.normalize(),
                }
            }
            "hull" => {
                let raw = self.points_m.as_deref().unwrap_or_default();
                let mut points = Vec::with_capacity(raw.len());
                for (i, p) in raw.iter().enumerate() {
                    points.push(checker.finite3(format!("{key}.points_m[{i}]"), *p)?);
                }
                hull(file, &k("points_m"), points)?
            }
            _ => {
                let name = self.mesh.as_deref().ok_or_else(|| {
                    ConfigError::invalid(
                        file,
                        &k("mesh"),
                        Verbatim("missing"),
                        "required for a mesh (an STL or OBJ file)",
                    )
                })?;
                hull(file, &k("mesh"), read_mesh(&k("mesh"), name)?)?
            }
        };
        let translation = checker.finite3(k("origin_xyz_m"), self.origin_xyz_m)?;
        let rpy = checker.finite3(k("origin_rpy_deg"), self.origin_rpy_deg)?;
        Ok(Collision {
            origin: origin_from_xyz_rpy(translation, rpy * (std::f64::consts::PI / 180.0)),
            shape,
        })
    }
}

/// The fewest points that span a solid.
const MIN_HULL_POINTS: usize = 4;

/// A hull of `points`, refused when they cannot span a solid (fewer than four, or all on
/// one plane: the checker needs a volume).
pub(crate) fn hull(file: &Path, key: &str, points: Vec<DVec3>) -> Result<Shape, ConfigError> {
    if points.len() < MIN_HULL_POINTS || !spans_volume(&points) {
        return Err(ConfigError::invalid(
            file,
            key,
            Verbatim(format!("{} points", points.len())),
            "a hull needs at least four points not on one plane",
        ));
    }
    Ok(Shape::ConvexHull { points })
}

/// The smallest volume, relative to the cube of the points' extent, that counts as a solid
/// (a flat scan of a plate is not one).
const FLAT_RATIO: f64 = 1e-9;

fn spans_volume(points: &[DVec3]) -> bool {
    let first = points[0];
    let extent = points
        .iter()
        .map(|p| (*p - first).length())
        .fold(0.0, f64::max);
    if extent <= 0.0 {
        return false;
    }
    // The farthest point from the first, then the farthest from that line, then from that
    // plane: a nonzero tetrahedron means a volume.
    let far = |score: &dyn Fn(DVec3) -> f64| {
        points
            .iter()
            .copied()
            .max_by(|a, b| score(*a).total_cmp(&score(*b)))
            .unwrap_or(first)
    };
    let b = far(&|p| (p - first).length());
    let line = (b - first).normalize_or_zero();
    let c = far(&|p| (p - first).cross(line).length());
    let normal = (b - first).cross(c - first).normalize_or_zero();
    let d = far(&|p| (p - first).dot(normal).abs());
    (d - first).dot(normal).abs() * (b - first).cross(c - first).length()
        > FLAT_RATIO * extent.powi(3)
}

/// One `[[body]]` table of a rig file: a link's name, its frame, and its solids.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawBody {
    name: String,
    frame: usize,
    #[serde(default)]
    collision: Vec<RawSolid>,
}

/// Validates a rig file's `[[body]]` tables against its `dof` joints and its
/// `allowed_pairs`: unique names, frames 0..=dof, at least one solid each, no half-space on
/// a moving link (it would be unbounded), and pairs naming bodies of the rig.
pub(crate) fn bodies_from_raw(
    file: &Path,
    raw: &[RawBody],
    dof: usize,
    read_mesh: &MeshReader<'_>,
) -> Result<Vec<LinkBody>, ConfigError> {
    let mut bodies: Vec<LinkBody> = Vec::with_capacity(raw.len());
    for (i, body) in raw.iter().enumerate() {
        let key = format!("body[{i}]");
        if body.name.trim().is_empty() {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}.name"),
                &body.name,
                "must not be empty",
            ));
        }
        if bodies.iter().any(|b| b.name == body.name) {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}.name"),
                &body.name,
                "duplicate body name",
            ));
        }
        if body.frame > dof {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}.frame"),
                body.frame,
                &format!("must lie in [0, {dof}] (0: the base, k: after joint k)"),
            ));
        }
        if body.collision.is_empty() {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}.collision"),
                Verbatim("[]"),
                "a body needs at least one solid",
            ));
        }
        let mut collisions = Vec::with_capacity(body.collision.len());
        for (j, solid) in body.collision.iter().enumerate() {
            let solid_key = format!("{key}.collision[{j}]");
            if solid.name.is_some() {
                return Err(ConfigError::invalid(
                    file,
                    &format!("{solid_key}.name"),
                    solid.name.as_deref(),
                    "a body's solids share the body's `name`",
                ));
            }
            let collision = solid.validate(file, &solid_key, read_mesh)?;
            if body.frame > 0 && matches!(collision.shape, Shape::HalfSpace { .. }) {
                return Err(ConfigError::invalid(
                    file,
                    &format!("{solid_key}.shape"),
                    "half_space",
                    "a half-space is unbounded: only the base (frame 0) may carry one",
                ));
            }
            collisions.push(collision);
        }
        bodies.push(LinkBody {
            name: body.name.clone(),
            frame: body.frame,
            collisions,
        });
    }
    Ok(bodies)
}

/// Checks `pairs` (at `key`) name two different bodies among `names`.
pub(crate) fn check_pairs<'a>(
    file: &Path,
    key: &str,
    pairs: &[(String, String)],
    names: impl Fn(&str) -> bool + 'a,
) -> Result<(), ConfigError> {
    for (i, (a, b)) in pairs.iter().enumerate() {
        for name in [a, b] {
            if !names(name) {
                return Err(ConfigError::invalid(
                    file,
                    &format!("{key}[{i}]"),
                    name,
                    "names no body",
                ));
            }
        }
        if a == b {
            return Err(ConfigError::invalid(
                file,
                &format!("{key}[{i}]"),
                a,
                "a pair needs two different bodies",
            ));
        }
    }
    Ok(())
}
