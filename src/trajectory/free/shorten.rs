//! Making a found path short and smooth, without leaving what is proven clear. Three
//! passes, each keeping the path's ends:
//!
//! - greedy shortcutting: from each kept waypoint, straight to the farthest later waypoint
//!   the checker proves reachable (the "path pruning" of Geraerts and Overmars 2007,
//!   "Creating high-quality paths for motion planning", IJRR 26(8));
//! - random shortcutting: two random points on the path, on different stretches, joined
//!   straight when that stretch is clear (the same paper's random shortcut);
//! - corner cutting (Chaikin 1974, "An algorithm for high-speed curve generation",
//!   Computer Graphics and Image Processing 3(4)): each corner is replaced by the points a
//!   quarter of the way along its two stretches, when the cut between them is clear.
//!
//! Every stretch of the result is either one the checker proved, or a piece of one (which
//! the proof covers: it holds at every point of a stretch). Owns the passes; the checks
//! are the [`Checker`]'s.

use super::checker::Checker;
use super::rrt::Sampler;
use super::{distance, lerp};
use rand::RngExt;

/// How far along each stretch from a corner its cut begins: Chaikin's quarter, which keeps
/// the cuts of neighbouring corners apart (a quarter from each end of a stretch).
const CORNER_CUT: f64 = 0.25;

/// How far (relative to its stretches' lengths) a waypoint may lie off the straight line
/// through its neighbours and still be dropped as on it: float rounding of the trees'
/// steps along one line, nothing a check could tell apart.
const COLLINEAR: f64 = 1e-9;

/// `path` without the waypoints that lie on the straight line between their neighbours
/// (a tree's CONNECT steps along one line): the stretch that replaces two is the same
/// proven line, and the greedy pass then has fewer waypoints to try.
pub(super) fn merge_collinear(path: Vec<Vec<f64>>) -> Vec<Vec<f64>> {
    let mut kept: Vec<Vec<f64>> = Vec::with_capacity(path.len());
    for point in path {
        if kept.len() >= 2 {
            let (a, b) = (&kept[kept.len() - 2], &kept[kept.len() - 1]);
            let (ab, bc, ac) = (distance(a, b), distance(b, &point), distance(a, &point));
            if ab + bc - ac <= COLLINEAR * (ab + bc) {
                kept.pop();
            }
        }
        kept.push(point);
    }
    kept
}

/// Greedy shortcutting: from the first waypoint, the farthest later waypoint reachable in
/// a straight clear stretch, and so on to the last.
pub(super) fn greedy(checker: &Checker, path: Vec<Vec<f64>>) -> Vec<Vec<f64>> {
    let last = path.len() - 1;
    let mut kept = vec![0];
    let mut from = 0;
    while from < last {
        // The next waypoint is always reachable: its stretch was proven.
        let to = (from + 2..=last)
            .rev()
            .find(|&to| checker.edge(&path[from], &path[to]))
            .unwrap_or(from + 1);
        kept.push(to);
        from = to;
    }
    kept.into_iter().map(|index| path[index].clone()).collect()
}

/// `attempts` random shortcuts: two points drawn uniformly along the path's length, joined
/// straight when they lie on different stretches and the stretch between them is clear.
pub(super) fn random(
    checker: &Checker,
    mut path: Vec<Vec<f64>>,
    attempts: usize,
    rng: &mut Sampler,
) -> Vec<Vec<f64>> {
    for _ in 0..attempts {
        let total: f64 = super::path_length(&path);
        if path.len() < 3 || total <= 0.0 {
            break;
        }
        let (s, t) = (rng.random_range(0.0..total), rng.random_range(0.0..total));
        let (i, a) = point_at(&path, s.min(t));
        let (j, b) = point_at(&path, s.max(t));
        if i == j || !checker.edge(&a, &b) {
            continue;
        }
        let mut shorter: Vec<Vec<f64>> = path[..=i].to_vec();
        for point in [a, b] {
            if shorter.last() != Some(&point) {
                shorter.push(point);
            }
        }
        for point in &path[j + 1..] {
            if shorter.last() != Some(point) {
                shorter.push(point.clone());
            }
        }
        path = shorter;
    }
    path
}

/// The stretch `length` along `path` lies on (index of its first waypoint) and the point.
fn point_at(path: &[Vec<f64>], length: f64) -> (usize, Vec<f64>) {
    let mut left = length;
    for (index, pair) in path.windows(2).enumerate() {
        let stretch = distance(&pair[0], &pair[1]);
        if left <= stretch && stretch > 0.0 {
            return (index, lerp(&pair[0], &pair[1], left / stretch));
        }
        left -= stretch;
    }
    let last = path.len() - 1;
    (last - 1, path[last].clone())
}

/// `rounds` rounds of corner cutting: each corner whose cut is clear becomes two points,
/// a quarter of the way along each of its stretches.
pub(super) fn cut_corners(
    checker: &Checker,
    mut path: Vec<Vec<f64>>,
    rounds: usize,
) -> Vec<Vec<f64>> {
    for _ in 0..rounds {
        if path.len() < 3 {
            break;
        }
        let mut cut = vec![path[0].clone()];
        for corner in path.windows(3) {
            let (before, at, after) = (&corner[0], &corner[1], &corner[2]);
            let p = lerp(at, before, CORNER_CUT);
            let q = lerp(at, after, CORNER_CUT);
            if checker.edge(&p, &q) {
                cut.push(p);
                cut.push(q);
            } else {
                cut.push(at.clone());
            }
        }
        cut.push(path[path.len() - 1].clone());
        path = cut;
    }
    path
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Steps along one line become one stretch; a bend, and a point 1 mm off the line, stay.
    #[test]
    fn only_waypoints_on_the_line_through_their_neighbours_are_merged() {
        let path = vec![
            vec![0.0, 0.0],
            vec![0.35, 0.0],
            vec![0.7, 0.0],
            vec![1.0, 0.0],
            vec![1.0, 0.5],
            vec![1.0, 1.0],
            vec![1.001, 1.5],
            vec![1.0, 2.0],
        ];
        let merged = merge_collinear(path);
        assert_eq!(
            merged,
            vec![
                vec![0.0, 0.0],
                vec![1.0, 0.0],
                vec![1.0, 1.0],
                vec![1.001, 1.5],
                vec![1.0, 2.0],
            ]
        );
    }
}
