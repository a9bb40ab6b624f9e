//! Protocol version 3's digital I/O messages (docs/protocol.md 3.6, 6.10): what the bridge
//! asks of a controller's outputs and inputs and what the controller answers, in memory.
//! The byte layout is `codec.rs`'s and the CAN segments `can.rs`'s; this file owns the
//! types and the rule for a name. It must not know sessions, links or the twin's gripper.

/// The longest I/O name on the wire, in bytes.
pub const MAX_IO_NAME_LEN: usize = 32;

/// A name is 1 to 32 ASCII letters, digits or `_` (docs/protocol.md 3.6): the same on
/// every controller, so a program's name is checked before it is sent.
pub fn io_name_ok(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= MAX_IO_NAME_LEN
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
}

/// Whether an [`IoState`] answers about an output or an input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IoKind {
    Output,
    Input,
}

impl IoKind {
    pub fn word(self) -> &'static str {
        match self {
            IoKind::Output => "output",
            IoKind::Input => "input",
        }
    }
}

/// What the controller did with a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IoResult {
    /// Set (an output, once it has taken effect) or read (an input).
    Done,
    /// The controller has no output or input of that name.
    NoSuch,
    /// Refused now: unbound, faulted, or the same output's last request still unanswered.
    Refused,
}

impl IoResult {
    pub fn words(self) -> &'static str {
        match self {
            IoResult::Done => "done",
            IoResult::NoSuch => "the controller has none of that name",
            IoResult::Refused => {
                "refused by the controller (unbound, faulted, or a request for it unanswered)"
            }
        }
    }
}

/// The controller's answer to one request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IoState {
    pub request: u32,
    pub kind: IoKind,
    pub result: IoResult,
    /// The output's value once set or the input's when read; false unless `Done`.
    pub value: bool,
    pub name: String,
}

/// An I/O message of either side.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum IoMessage {
    /// Bridge: set output `name` to `value`.
    SetOutput {
        request: u32,
        name: String,
        value: bool,
    },
    /// Bridge: read input `name`.
    ReadInput { request: u32, name: String },
    /// Controller: the answer to one request.
    State(IoState),
}

impl IoMessage {
    /// The request number it carries or answers.
    pub fn request(&self) -> u32 {
        match self {
            IoMessage::SetOutput { request, .. } | IoMessage::ReadInput { request, .. } => *request,
            IoMessage::State(state) => state.request,
        }
    }
}
