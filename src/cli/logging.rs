//! Where the library's diagnostics (its `tracing` events) go: one subscriber for the process.
//! By default an event prints as its message alone, one line, exactly as the commands have
//! always printed it: rigbridge's own events at info and above, the twin's (target
//! `rigbridge::twin`) on stdout, where its users and tests read them line by line, all
//! others on stderr. `RUST_LOG` (an EnvFilter) asks for more on stderr, each event then with
//! its time, level, target and fields. Owns no message: those are the library's.

use std::fmt::Debug;
use tracing::field::{Field, Visit};
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::filter::{EnvFilter, FilterExt, LevelFilter, Targets};
use tracing_subscriber::fmt::format::Writer;
use tracing_subscriber::fmt::{FmtContext, FormatEvent, FormatFields};
use tracing_subscriber::registry::LookupSpan;
use tracing_subscriber::{Layer, fmt, prelude::*};

/// What is printed when `RUST_LOG` does not say: rigbridge's events a user always saw, and
/// none of its dependencies' (zenoh, hyper) chatter.
const DEFAULT_FILTER: &str = "rigbridge=info";

/// The events of the twin's own processes: their output, one line per event on stdout
/// (with each device's twin side, `rigbridge::device::twin_log_targets`).
const TWIN_TARGET: &str = "rigbridge::twin";

/// The twin's targets: the shared twin's and each device's twin side's.
fn twin_targets() -> impl Iterator<Item = &'static str> {
    std::iter::once(TWIN_TARGET).chain(rigbridge::device::twin_log_targets())
}

/// Sets the subscriber up; called once, before any command runs.
pub fn init() {
    let default = || (EnvFilter::new(DEFAULT_FILTER), false);
    let (filter, detailed) = match std::env::var("RUST_LOG") {
        Ok(directives) if !directives.trim().is_empty() => {
            match EnvFilter::builder().parse(&directives) {
                Ok(filter) => (filter, true),
                Err(e) => {
                    eprintln!("note: RUST_LOG={directives} ignored ({e}); logging as by default");
                    default()
                }
            }
        }
        _ => default(),
    };
    let twin = fmt::layer()
        .event_format(Plain)
        .with_writer(std::io::stdout)
        .with_filter(Targets::new().with_targets(twin_targets().map(|t| (t, Level::INFO))));
    // Targets, not a closure: both decide once per call site, never per event (zenoh's
    // trace events on hot paths then cost nothing).
    let others = filter.and(
        Targets::new()
            .with_default(LevelFilter::TRACE)
            .with_targets(twin_targets().map(|t| (t, LevelFilter::OFF))),
    );
    let diagnostics = if detailed {
        fmt::layer()
            .with_ansi(false)
            .with_writer(std::io::stderr)
            .with_filter(others)
            .boxed()
    } else {
        fmt::layer()
            .event_format(Plain)
            .with_writer(std::io::stderr)
            .with_filter(others)
            .boxed()
    };
    // Only fails when a subscriber is already set: then that one stays.
    let _ = tracing_subscriber::registry()
        .with(twin)
        .with(diagnostics)
        .try_init();
}

/// An event as its message alone, the line a user has always read.
struct Plain;

impl<S, N> FormatEvent<S, N> for Plain
where
    S: Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
{
    fn format_event(
        &self,
        _context: &FmtContext<'_, S, N>,
        mut writer: Writer<'_>,
        event: &Event<'_>,
    ) -> std::fmt::Result {
        let mut message = Message {
            writer: &mut writer,
            written: Ok(()),
        };
        event.record(&mut message);
        message.written?;
        writeln!(writer)
    }
}

/// Writes an event's `message` field (the macros' format string, already formatted).
struct Message<'w, 'a> {
    writer: &'w mut Writer<'a>,
    written: std::fmt::Result,
}

impl Visit for Message<'_, '_> {
    fn record_debug(&mut self, field: &Field, value: &dyn Debug) {
        if field.name() == "message" {
            // The message is `format_args!`, whose Debug is its Display: no quotes.
            self.written = write!(self.writer, "{value:?}");
        }
    }
}
