//! Checks of a run log read back with `rigbridge::log::read_log`, from the log alone: where
//! the stream resumed from a hold, and that after a lost link it moved on from where the
//! controller held, one cycle's travel at a time. Owns no run: the callers make the log.

use rigbridge::log::RunLog;
use rigbridge::rig::Rig;

/// Where the stream resumed from a hold (a link loss, or a stall on a loaded machine): the
/// job time of each `resumed` event and the actual position it names, in the log's order.
pub fn resumptions(log: &RunLog) -> Vec<(f64, Vec<f64>)> {
    log.events
        .iter()
        .filter(|e| e.kind == "resumed")
        .map(|e| {
            (
                e.t,
                serde_json::from_value(e.detail["actual"].clone()).unwrap(),
            )
        })
        .collect()
}

/// After the log's first interruption (`link_lost`, or `stalled`: on a slow emulated
/// machine a stall can come first, and the link's loss then falls within its wait for the
/// hold, with no event of its own): the stream resumed at least once, and every resumption
/// starts from where the controller held (docs/protocol.md 6.8), so that from there on
/// every command is within one cycle's travel (max speed x `period`) of the one before.
#[track_caller]
pub fn assert_resumes_in_step_after_link_loss(log: &RunLog, rig: &Rig, period: f64) {
    let resumes = resumptions(log);
    assert!(!resumes.is_empty(), "a resumed event");
    let lost_at = log
        .events
        .iter()
        .find(|e| e.kind == "link_lost" || e.kind == "stalled")
        .expect("a link_lost or stalled event")
        .t;
    let mut previous: Option<Vec<f64>> = None;
    let mut next_resume = 0;
    for command in log.commands.iter().filter(|c| c.t > lost_at + 1e-9) {
        while next_resume < resumes.len() && resumes[next_resume].0 < command.t {
            previous = Some(resumes[next_resume].1.clone());
            next_resume += 1;
        }
        let Some(before) = &previous else { continue };
        for ((q, p), joint) in command.positions.iter().zip(before).zip(&rig.joints) {
            assert!(
                (q - p).abs() <= joint.limits.max_speed * period * (1.0 + 1e-9),
                "step at seq {}",
                command.seq
            );
        }
        previous = Some(command.positions.clone());
    }
}
