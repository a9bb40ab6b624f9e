//! Where each stretch of a trajectory came from, in the words its user wrote it: the move to
//! `job.targets_deg[2]`, the line to `job.poses[1]`, the piece after row 14 of `t.csv`,
//! the log's command seq 812. A refusal of the motion (the collision check before motion)
//! names the stretch its first offending sample lies in. Owns only this mapping from
//! sample index to words; the planners say where their waypoints sit, the jobs what to
//! call them.

/// Stretches in order, each the samples up to and including its last one.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Origins {
    /// (last sample of the stretch, what it came from), last samples non-decreasing.
    stretches: Vec<(usize, String)>,
}

impl Origins {
    /// One stretch for the whole trajectory.
    pub fn whole(what: impl Into<String>) -> Origins {
        Origins {
            stretches: vec![(usize::MAX, what.into())],
        }
    }

    /// The samples after the last stretch, up to and including `last`, came from `what`.
    pub fn push(&mut self, last: usize, what: impl Into<String>) {
        self.stretches.push((last, what.into()));
    }

    /// A stretch per waypoint: `marks[k]` the sample waypoint `k` sits at (as the planners
    /// give them), shifted by `offset` samples, named by `name(k)`.
    pub fn push_marks(&mut self, marks: &[usize], offset: usize, name: impl Fn(usize) -> String) {
        for (k, mark) in marks.iter().enumerate() {
            self.push(mark + offset, name(k));
        }
    }

    /// The last sample of each stretch, in order.
    pub fn ends(&self) -> impl Iterator<Item = usize> + '_ {
        self.stretches.iter().map(|(last, _)| *last)
    }

    /// What sample `sample` came from: the first stretch that reaches it (a sample past the
    /// last stretch, the last one; none given, the whole job).
    pub fn at(&self, sample: usize) -> &str {
        self.stretches
            .iter()
            .find(|(last, _)| *last >= sample)
            .or(self.stretches.last())
            .map_or("the job's trajectory", |(_, what)| what.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sample_is_named_by_the_first_stretch_that_reaches_it() {
        let mut origins = Origins::default();
        origins.push_marks(&[0, 10, 25], 0, |k| format!("job.targets_deg[{k}]"));
        origins.push(40, "the return");
        // Sample 0 is the start itself (a zero-length first move): the first target's.
        assert_eq!(origins.at(0), "job.targets_deg[0]");
        assert_eq!(origins.at(1), "job.targets_deg[1]");
        assert_eq!(origins.at(10), "job.targets_deg[1]");
        assert_eq!(origins.at(11), "job.targets_deg[2]");
        assert_eq!(origins.at(26), "the return");
        assert_eq!(origins.at(99), "the return");
        assert_eq!(Origins::default().at(3), "the job's trajectory");
        assert_eq!(Origins::whole("the gait").at(7), "the gait");
    }
}
