//! Terrain: branches and trunks as finite cylinders (axis from, to, radius). Owns the
//! geometry questions the gait asks (distances to surfaces, capsule clearance, ray traces);
//! it must not know about limbs or steps.

use glam::DVec3;
use serde::Serialize;

/// One branch or trunk. Travel along it runs from `from` to `to`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Cylinder {
    pub from: DVec3,
    pub to: DVec3,
    pub radius: f64,
}

/// Where a ray meets a cylinder's side.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub support: usize,
    pub distance: f64,
    pub point: DVec3,
    /// Outward unit normal of the surface at the hit.
    pub normal: DVec3,
}

impl Cylinder {
    pub fn direction(&self) -> DVec3 {
        (self.to - self.from).normalize_or_zero()
    }

    pub fn length(&self) -> f64 {
        self.from.distance(self.to)
    }

    /// Angle of the axis above (positive) or below the horizontal, along travel.
    pub fn slope(&self) -> f64 {
        self.direction().z.clamp(-1.0, 1.0).asin()
    }

    /// Tilted more than `threshold` from horizontal either way: a trunk.
    pub fn is_trunk(&self, threshold: f64) -> bool {
        self.slope().abs() > threshold
    }

    /// The axis parameter (0 at `from`, 1 at `to`) of the point nearest `p`, unclamped.
    pub fn parameter(&self, p: DVec3) -> f64 {
        let axis = self.to - self.from;
        (p - self.from).dot(axis) / axis.length_squared()
    }

    pub fn axis_point(&self, parameter: f64) -> DVec3 {
        self.from + (self.to - self.from) * parameter
    }

    /// Distance from `p` to the axis segment, minus the radius: negative inside.
    pub fn signed_distance(&self, p: DVec3) -> f64 {
        let nearest = self.axis_point(self.parameter(p).clamp(0.0, 1.0));
        p.distance(nearest) - self.radius
    }

    /// Gap between a capsule (segment `a`-`b`, `radius`) and this cylinder (as a capsule):
    /// negative when they overlap.
    pub fn capsule_clearance(&self, a: DVec3, b: DVec3, radius: f64) -> f64 {
        segment_distance(a, b, self.from, self.to) - radius - self.radius
    }

    /// The first crossing of the side surface by the ray `origin + t direction`, `t >= 0`,
    /// within the axis' extent; caps are not traced (supports are long).
    pub fn trace(&self, origin: DVec3, direction: DVec3) -> Option<(f64, DVec3)> {
        let axis = self.direction();
        let relative = origin - self.from;
        let d = direction - axis * direction.dot(axis);
        let m = relative - axis * relative.dot(axis);
        let a = d.length_squared();
        if a < 1e-15 {
            return None;
        }
        let b = 2.0 * d.dot(m);
        let c = m.length_squared() - self.radius * self.radius;
        let discriminant = b * b - 4.0 * a * c;
        if discriminant < 0.0 {
            return None;
        }
        let root = discriminant.sqrt();
        [(-b - root) / (2.0 * a), (-b + root) / (2.0 * a)]
            .into_iter()
            .filter(|t| *t >= 0.0)
            .map(|t| (t, origin + direction * t))
            .find(|(_, p)| (0.0..=1.0).contains(&self.parameter(*p)))
    }

    /// Outward unit normal of the side surface nearest `p`.
    pub fn normal_at(&self, p: DVec3) -> DVec3 {
        let nearest = self.axis_point(self.parameter(p));
        (p - nearest).normalize_or_zero()
    }
}

/// All supports of a scene.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Terrain {
    pub cylinders: Vec<Cylinder>,
}

impl Terrain {
    /// The nearest surface crossing along a ray, over every support.
    pub fn trace(&self, origin: DVec3, direction: DVec3) -> Option<Hit> {
        let direction = direction.normalize_or_zero();
        self.cylinders
            .iter()
            .enumerate()
            .filter_map(|(support, cylinder)| {
                cylinder
                    .trace(origin, direction)
                    .map(|(distance, point)| Hit {
                        support,
                        distance,
                        point,
                        normal: cylinder.normal_at(point),
                    })
            })
            .min_by(|a, b| a.distance.total_cmp(&b.distance))
    }

    /// The least signed distance from `p` to any support (negative: inside one).
    pub fn clearance(&self, p: DVec3) -> f64 {
        self.cylinders
            .iter()
            .map(|c| c.signed_distance(p))
            .fold(f64::INFINITY, f64::min)
    }

    /// The least gap between a capsule and any support.
    pub fn capsule_clearance(&self, a: DVec3, b: DVec3, radius: f64) -> f64 {
        self.cylinders
            .iter()
            .map(|c| c.capsule_clearance(a, b, radius))
            .fold(f64::INFINITY, f64::min)
    }
}

/// The least distance between segments `p0`-`p1` and `q0`-`q1`.
pub fn segment_distance(p0: DVec3, p1: DVec3, q0: DVec3, q1: DVec3) -> f64 {
    let (p, q) = segment_nearest(p0, p1, q0, q1);
    p.distance(q)
}

/// The points of segments `p0`-`p1` and `q0`-`q1` nearest each other (the first of them
/// along `p0`-`p1` when there are many, as for parallel segments).
pub fn segment_nearest(p0: DVec3, p1: DVec3, q0: DVec3, q1: DVec3) -> (DVec3, DVec3) {
    let d1 = p1 - p0;
    let d2 = q1 - q0;
    let r = p0 - q0;
    let a = d1.length_squared();
    let e = d2.length_squared();
    let f = d2.dot(r);
    let (s, t) = if a <= 1e-18 && e <= 1e-18 {
        (0.0, 0.0)
    } else if a <= 1e-18 {
        (0.0, (f / e).clamp(0.0, 1.0))
    } else {
        let c = d1.dot(r);
        if e <= 1e-18 {
            ((-c / a).clamp(0.0, 1.0), 0.0)
        } else {
            let b = d1.dot(d2);
            let denominator = a * e - b * b;
            let mut s = if denominator > 1e-18 {
                ((b * f - c * e) / denominator).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let mut t = (b * s + f) / e;
            if t < 0.0 {
                t = 0.0;
                s = (-c / a).clamp(0.0, 1.0);
            } else if t > 1.0 {
                t = 1.0;
                s = ((b - c) / a).clamp(0.0, 1.0);
            }
            (s, t)
        }
    };
    (p0 + d1 * s, q0 + d2 * t)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn branch() -> Cylinder {
        Cylinder {
            from: DVec3::new(-1.0, 0.0, 0.0),
            to: DVec3::new(1.0, 0.0, 0.0),
            radius: 0.02,
        }
    }

    #[test]
    fn a_sideways_ray_hits_the_near_side() {
        let (t, p) = branch()
            .trace(DVec3::new(0.3, -0.5, 0.0), DVec3::Y)
            .expect("the sideways ray hits the branch");
        assert!((t - 0.48).abs() < 1e-12 && (p.y + 0.02).abs() < 1e-12);
        assert!(
            branch()
                .trace(DVec3::new(1.3, -0.5, 0.0), DVec3::Y)
                .is_none()
        );
    }

    #[test]
    fn segment_distance_of_crossing_and_parallel_segments() {
        let d = segment_distance(
            DVec3::new(0.0, -1.0, 0.5),
            DVec3::new(0.0, 1.0, 0.5),
            DVec3::new(-1.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
        );
        assert!((d - 0.5).abs() < 1e-12);
        let parallel = segment_distance(
            DVec3::new(2.0, 0.0, 0.3),
            DVec3::new(3.0, 0.0, 0.3),
            DVec3::new(-1.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
        );
        assert!((parallel - (1.0f64 + 0.09).sqrt()).abs() < 1e-12);
    }
}
