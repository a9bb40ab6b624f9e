//! A job given as TOML text rather than in a run settings file: the live page's pasted job,
//! sent as `{"toml": "..."}` to `POST .../jobs`. Owns only the parsing: the text is a
//! settings file's `[job]` table (or its keys alone), read into [`Job`] by the same serde
//! shape as the file, and the caller then validates it as it does every job
//! ([`Job::validate`]). A parse error names the line and column of the text.

use super::Job;
use serde::Deserialize;
use thiserror::Error;

/// Longest quote of a refused TOML message: a hostile text is not echoed back whole.
const MAX_MESSAGE_CHARS: usize = 300;

/// TOML text that is not a job, where and why.
#[derive(Debug, Error)]
#[error("pasted TOML, line {line}, column {column}: {message}")]
pub struct PastedJobError {
    /// 1-based, of the text as given.
    pub line: usize,
    pub column: usize,
    /// The TOML reader's own words (which key, which variant, which value).
    pub message: String,
}

/// A settings file's shape, with nothing but its `[job]`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JobTable {
    job: Job,
}

/// The job in `text`: a `[job]` table, or the job's keys (`kind = ...`) at the top level.
pub fn job_from_toml(text: &str) -> Result<Job, PastedJobError> {
    let as_table = |e: toml::de::Error| located(text, &e);
    let top: toml::Table = toml::from_str(text).map_err(as_table)?;
    if top.contains_key("job") {
        toml::from_str::<JobTable>(text)
            .map(|file| file.job)
            .map_err(as_table)
    } else {
        toml::from_str::<Job>(text).map_err(as_table)
    }
}

/// `error` with the line and column its span starts at in `text` (1, 1 without a span).
fn located(text: &str, error: &toml::de::Error) -> PastedJobError {
    let start = error.span().map_or(0, |span| span.start.min(text.len()));
    let before = text.get(..start).unwrap_or(text);
    let line = before.matches('\n').count() + 1;
    let column = before
        .rsplit('\n')
        .next()
        .map_or(0, |tail| tail.chars().count())
        + 1;
    let mut message = error.message().trim_end().to_string();
    if message.chars().count() > MAX_MESSAGE_CHARS {
        message = message.chars().take(MAX_MESSAGE_CHARS).collect::<String>() + "...";
    }
    PastedJobError {
        line,
        column,
        message,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_job_table_or_its_keys_alone_read_the_same() {
        let table = "[job]\nkind = \"move_joints\"\ntargets_deg = [[0, 0, 0, 0, 30, 0]]\n";
        let keys = "kind = \"move_joints\"\ntargets_deg = [[0, 0, 0, 0, 30, 0]]\n";
        let from_table = job_from_toml(table).expect("a [job] table");
        assert_eq!(from_table.kind(), "move_joints");
        assert_eq!(from_table, job_from_toml(keys).expect("the keys alone"));
    }

    #[test]
    fn a_bad_text_names_its_line_column_and_why() {
        let unknown = "[job]\nkind = \"dance\"\n";
        let e = job_from_toml(unknown).expect_err("no such kind");
        assert_eq!((e.line, e.column), (2, 8), "{e}");
        assert!(
            e.to_string()
                .starts_with("pasted TOML, line 2, column 8: unknown variant `dance`"),
            "{e}"
        );
        let broken = "kind = \"move_joints\"\ntargets_deg = [[0, 0,\n";
        let e = job_from_toml(broken).expect_err("an unclosed list");
        // Where the list should have closed: the end of line 2.
        assert_eq!((e.line, e.column), (2, 22), "{e}");
        assert!(e.message.contains("unclosed array"), "{e}");
        let missing = "[job]\nkind = \"move_joints\"\n";
        let e = job_from_toml(missing).expect_err("no targets");
        assert!(e.message.contains("missing field `targets_deg`"), "{e}");
        let extra = "[job]\nkind = \"move_joints\"\ntargets_deg = [[0, 0, 0, 0, 30, 0]]\n[stream]\nrate_hz = 1\n";
        let e = job_from_toml(extra).expect_err("only the job is taken");
        assert!(e.message.contains("unknown field `stream`"), "{e}");
        assert_eq!(e.line, 4, "{e}");
    }
}
