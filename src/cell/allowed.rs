//! Finding a rig's allowed pairs by sampling, as MoveIt's setup assistant does: bodies on
//! neighbouring frames (adjacent links), pairs in collision in every sampled configuration
//! (always), and pairs that never come near in any (never). The result goes into the rig
//! file's `allowed_pairs` (`rigbridge config allowed-pairs`). Owns the sampling and the
//! rewriting of that one key; the distances come from the collision model.

use super::{Cell, CellError, CollisionModel};
use crate::rig::Rig;
use std::collections::HashMap;

/// Configurations sampled: MoveIt's setup assistant's default density (10,000).
pub const DEFAULT_SAMPLES: usize = 10_000;

/// A pair counts as "never in collision" only when no sample brought it closer than this:
/// 50 mm leaves room for what the samples missed between them (MoveIt uses contact only;
/// we keep a distance, since a pair left out is never checked again).
pub const NEVER_CLEARANCE_M: f64 = 0.05;

/// Why a pair is allowed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reason {
    /// On neighbouring frames: the links meet at their joint.
    Adjacent,
    /// In collision in every sample.
    Always,
    /// Never closer than [`NEVER_CLEARANCE_M`] in any sample.
    Never,
}

impl std::fmt::Display for Reason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Reason::Adjacent => "adjacent",
            Reason::Always => "always in collision",
            Reason::Never => "never in collision",
        })
    }
}

/// One allowed pair and why.
#[derive(Debug, Clone, PartialEq)]
pub struct AllowedPair {
    pub a: String,
    pub b: String,
    pub reason: Reason,
    /// The smallest clearance seen over the samples (m).
    pub min_clearance_m: f64,
}

/// SplitMix64 (Steele, Lea, Flood 2014): a seeded, portable stream, so the same seed gives
/// the same pairs on every machine.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        // The top 53 bits as a fraction in [0, 1).
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// The allowed pairs of `rig`'s bodies (its own `allowed_pairs` ignored) from `samples`
/// configurations uniform within its limits, seeded by `seed`, plus the zero
/// configuration.
pub fn find_allowed_pairs(
    rig: &Rig,
    samples: usize,
    seed: u64,
) -> Result<Vec<AllowedPair>, CellError> {
    let bare = Rig {
        allowed_pairs: Vec::new(),
        ..rig.clone()
    };
    let empty = Cell {
        objects: Vec::new(),
        tool: None,
        allowed_pairs: Vec::new(),
        ..Cell::builtin()
    };
    let model = CollisionModel::new(&bare, &empty)?;
    let mut scratch = model.scratch();
    let mut rng = SplitMix64(seed);
    // Per pair: (smallest clearance, samples in collision).
    let mut seen: HashMap<(usize, usize), (f64, usize)> = HashMap::new();
    let mut within = Vec::new();
    let mut q = vec![0.0; rig.dof()];
    for sample in 0..=samples {
        if sample > 0 {
            for (value, joint) in q.iter_mut().zip(&rig.joints) {
                let l = joint.limits;
                *value = l.lower + rng.next_unit() * (l.upper - l.lower);
            }
        }
        model.pairs_within(&q, f64::INFINITY, &mut scratch, &mut within);
        for c in &within {
            let entry = seen.entry((c.a, c.b)).or_insert((f64::INFINITY, 0));
            entry.0 = entry.0.min(c.distance_m);
            entry.1 += usize::from(c.distance_m <= 0.0);
        }
    }
    let frame_of = |name: &str| rig.bodies.iter().find(|b| b.name == name).map(|b| b.frame);
    let mut allowed = Vec::new();
    for &(a, b) in model.checked_pairs() {
        let (name_a, name_b) = (model.body_name(a), model.body_name(b));
        let (min, hits) = seen.get(&(a, b)).copied().unwrap_or((f64::INFINITY, 0));
        let adjacent = match (frame_of(name_a), frame_of(name_b)) {
            (Some(fa), Some(fb)) => fa.abs_diff(fb) == 1,
            _ => false,
        };
        let reason = if adjacent {
            Some(Reason::Adjacent)
        } else if hits == samples + 1 {
            Some(Reason::Always)
        } else if min >= NEVER_CLEARANCE_M {
            Some(Reason::Never)
        } else {
            None
        };
        if let Some(reason) = reason {
            allowed.push(AllowedPair {
                a: name_a.to_string(),
                b: name_b.to_string(),
                reason,
                min_clearance_m: min,
            });
        }
    }
    Ok(allowed)
}

/// The TOML of `pairs` as a rig file's `allowed_pairs` key, each pair with its reason.
pub fn allowed_pairs_toml(pairs: &[AllowedPair]) -> String {
    let mut text = String::from("allowed_pairs = [\n");
    for pair in pairs {
        text.push_str(&format!(
            "    [\"{}\", \"{}\"], # {}, closest {:.3} m\n",
            pair.a.escape_default(),
            pair.b.escape_default(),
            pair.reason,
            pair.min_clearance_m
        ));
    }
    text.push(']');
    text
}

/// `rig_text` (a rig file) with its `allowed_pairs` key replaced by `key_text`, or added
/// before its first table when it has none.
pub fn replace_allowed_pairs(rig_text: &str, key_text: &str) -> String {
    let starts: Vec<usize> = std::iter::once(0)
        .chain(rig_text.match_indices('\n').map(|(i, _)| i + 1))
        .filter(|&i| i < rig_text.len())
        .collect();
    let key_line = starts
        .iter()
        .copied()
        .find(|&i| rig_text[i..].trim_start().starts_with("allowed_pairs"));
    if let Some(start) = key_line
        && let Some(end) = array_end(rig_text, start)
    {
        return format!("{}{}{}", &rig_text[..start], key_text, &rig_text[end..]);
    }
    let first_table = starts
        .iter()
        .copied()
        .find(|&i| rig_text[i..].starts_with('['))
        .unwrap_or(rig_text.len());
    format!(
        "{}{}\n\n{}",
        &rig_text[..first_table],
        key_text,
        &rig_text[first_table..]
    )
}

/// The byte after the `]` closing the array that starts on the line at `start` (strings and
/// comments inside skipped).
fn array_end(text: &str, start: usize) -> Option<usize> {
    let mut depth = 0usize;
    let mut in_string = false;
    let mut in_comment = false;
    for (offset, ch) in text[start..].char_indices() {
        match ch {
            '\n' => in_comment = false,
            _ if in_comment => {}
            '"' => in_string = !in_string,
            _ if in_string => {}
            '#' => in_comment = true,
            '[' => depth += 1,
            ']' => {
                depth = depth.checked_sub(1)?;
                if depth == 0 {
                    return Some(start + offset + 1);
                }
            }
            _ => {}
        }
    }
    None
}
