//! The device protocols rigbridge speaks to a controller, one folder each: our own protocol
//! over TCP, serial and CAN (`ours`), ABB EGM (`egm`), CiA 402 over CANopen (`canopen`) and
//! Dynamixel Protocol 2.0 (`dynamixel`). A folder holds its protocol's wire codec, its link
//! (the bridge's side), its twin side (the device played for tests and `rigbridge twin`)
//! and their settings; what the links of several protocols share is here too (`bus`, the
//! I/O thread of the links that master a bus of devices) and the link addresses users
//! write (`spec`).
//!
//! It sits between the streamer and the shared link and twin machinery: it may import
//! `link` (the `Link` trait, the session state machine, the channel), `twin` (the strict
//! controller model and its port and session over a byte transport), `transport` and
//! `protocol`; none of those imports it.

mod bus;
pub mod canopen;
pub mod dynamixel;
pub mod egm;
pub mod ours;
mod spec;

pub use spec::{LinkSpec, LinkSpecError, link_forms};

/// One device protocol as the link address parser, the twin's command line and the config
/// see it: after openrr's `arci`, one small trait for one capability (here: being
/// addressed). What a protocol does once addressed is its own folder's.
pub trait Backend: Sync {
    /// The link address schemes it answers (`egm` for `egm://...`).
    fn schemes(&self) -> &'static [&'static str];
    /// Its address forms, as the command line's help and a bad address's error list them.
    fn forms(&self) -> &'static str;
    /// The address of one of its `scheme`s, `rest` being the text after `scheme://`; an
    /// error says what is wrong with it in words.
    fn parse(&self, scheme: &str, rest: &str) -> Result<LinkSpec, &'static str>;
    /// The `rigbridge twin` flags that play it.
    fn twin_flags(&self) -> &'static [&'static str];
    /// The tracing target its twin side logs under (its module path), whose events the
    /// twin's process prints on stdout, where its users and tests read them line by line.
    fn twin_log_target(&self) -> &'static str;
}

/// Every device protocol rigbridge speaks, the one list the link address parser, the
/// help's list of address forms and the twin's command line read. A new protocol is its
/// folder and its line here.
pub const BACKENDS: &[&dyn Backend] = &[
    &ours::Ours,
    &egm::Egm,
    &canopen::Canopen,
    &dynamixel::Dynamixel,
];

/// Every device twin's tracing target ([`Backend::twin_log_target`]).
pub fn twin_log_targets() -> impl Iterator<Item = &'static str> {
    BACKENDS.iter().map(|backend| backend.twin_log_target())
}

/// Every `rigbridge twin` flag that chooses what the twin plays, as its error lists them.
pub fn twin_flags() -> String {
    let flags: Vec<&str> = BACKENDS
        .iter()
        .flat_map(|backend| backend.twin_flags().iter().copied())
        .collect();
    flags.join(", ")
}

#[cfg(test)]
mod tests {
    use super::BACKENDS;

    /// The twin's "choose one" error names every way to run it, `--canopen` included (the
    /// text written by hand left it out).
    #[test]
    fn the_twin_error_names_every_protocol() {
        let text = super::twin_flags();
        for flag in [
            "--listen",
            "--serial",
            "--pty",
            "--can",
            "--egm",
            "--canopen",
            "--dynamixel",
        ] {
            assert!(
                text.split(", ").any(|f| f == flag),
                "{flag} missing: {text}"
            );
        }
    }

    /// Each link address scheme is answered by exactly one backend.
    #[test]
    fn every_scheme_has_one_backend() {
        let mut schemes: Vec<&str> = BACKENDS
            .iter()
            .flat_map(|backend| backend.schemes().iter().copied())
            .collect();
        schemes.sort_unstable();
        assert_eq!(
            schemes,
            ["can", "canopen", "dynamixel", "egm", "serial", "tcp"]
        );
    }
}
