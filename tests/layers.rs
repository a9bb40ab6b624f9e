//! Imports point down only (issue 19): every file under `src/` may name, by a `crate::`
//! path or a `super::` chain that leaves its top module, only its own top module or one
//! below it in [`LAYERS`]. `docs/architecture.md` ("Layers") shows the same list, which
//! the second test checks; the third checks the list names every module exactly once.
//!
//! A file is read up to its `#[cfg(test)]` module (tests may reach anywhere), with its
//! comments and string literals blanked out: a doc link or a message is not an import.

use crate::common;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// The one layer order, top to bottom: a module may import any module below it, never one
/// above. The binary's `src/main.rs` and `src/cli/` count as `cli`.
const LAYERS: &[&str] = &[
    "cli",
    "server",
    "daemon",
    "apps",
    "batch",
    "ros2",
    "view",
    "job",
    "ik",
    "trajectory",
    "stream",
    "device",
    "link",
    "twin",
    "log",
    "motion",
    "scene",
    "transport",
    "protocol",
    "cell",
    "rig",
    "clock",
    "realtime",
];

/// Imports that still point up, each with the file, the module it names and why: the
/// demo apps' moves out of the core (issue 31 item 2) left these for the app interface to
/// remove. The first test fails on any other upward import, and on an entry here that no
/// longer happens (so the list only shrinks).
const PENDING_UPWARD: &[(&str, &str, &str)] = &[
    (
        "src/job/mod.rs",
        "apps",
        "the Job enum (one serde-tagged enum, which keeps the job formats) still lists the \
         paint and gait kinds, and JobError their errors",
    ),
    (
        "src/apps/paint/run.rs",
        "daemon",
        "`rigbridge paint`'s end-to-end run streams through the daemon",
    ),
    (
        "src/apps/gait/run.rs",
        "daemon",
        "`rigbridge gait`'s end-to-end run streams through the daemon",
    ),
];

fn src_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

#[test]
fn no_module_imports_one_above_it() {
    let mut offences = Vec::new();
    let mut pending_seen = BTreeSet::new();
    for file in common::rust_files(&src_dir()) {
        let relative = file.strip_prefix(src_dir()).unwrap();
        let Some(module) = module_path(relative) else {
            continue;
        };
        let shown = format!("src/{}", relative.display());
        let text = std::fs::read_to_string(&file).unwrap();
        for (line, target) in imports(&module, &text) {
            let Some(why) = offence(&module[0], &target) else {
                continue;
            };
            match PENDING_UPWARD
                .iter()
                .position(|(f, t, _)| *f == shown && *t == target)
            {
                Some(entry) => {
                    pending_seen.insert(entry);
                }
                None => offences.push(format!("{shown}:{line}: {why}")),
            }
        }
    }
    for (entry, (file, target, _)) in PENDING_UPWARD.iter().enumerate() {
        if !pending_seen.contains(&entry) {
            offences.push(format!(
                "{file} no longer imports {target}: take it off PENDING_UPWARD"
            ));
        }
    }
    assert!(
        offences.is_empty(),
        "{} import(s) against the layer order:\n{}",
        offences.len(),
        offences.join("\n")
    );
}

#[test]
fn the_architecture_doc_shows_the_same_order() {
    let doc_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/architecture.md");
    let doc = std::fs::read_to_string(doc_path).unwrap();
    let section = doc
        .split("\n## Layers")
        .nth(1)
        .expect("docs/architecture.md has a `## Layers` section");
    let section = section.split("\n## ").next().unwrap();
    // The list's items: "1. `cli`: why ...".
    let listed: Vec<&str> = section
        .lines()
        .filter_map(|line| {
            let (number, rest) = line.split_once(". `")?;
            number.parse::<usize>().ok()?;
            rest.split('`').next()
        })
        .collect();
    assert_eq!(listed, LAYERS, "docs/architecture.md's Layers list");
}

#[test]
fn the_order_names_every_module_once() {
    let lib = std::fs::read_to_string(src_dir().join("lib.rs")).unwrap();
    let mut modules: BTreeSet<&str> = lib
        .lines()
        .filter_map(|line| line.strip_prefix("pub mod ")?.strip_suffix(';'))
        .collect();
    modules.insert("cli");
    let layers: BTreeSet<&str> = LAYERS.iter().copied().collect();
    assert_eq!(layers.len(), LAYERS.len(), "a module is listed twice");
    assert_eq!(layers, modules, "LAYERS against src/lib.rs's modules");
}

/// The checker finds what it must and nothing else, on a made-up file of `log` (whose
/// module path is `log::replay`).
#[test]
fn the_checker_reads_paths_groups_and_super_chains() {
    let text = r#"//! See [`x`](crate::view::SceneView).
use crate::rig::Rig;
use crate::{protocol::Command, trajectory::{Trajectory, validate}};
use super::LogError;
fn f() -> u8 { let _ = "crate::job"; /* crate::daemon */ crate::view::f(); 'a' as u8 }
fn g<'a>(x: &'a str) -> &'a str { super::super::stream::h(); x }
#[cfg(test)]
mod tests {
    use crate::daemon::Anything;
}
"#;
    let module = ["log".to_owned(), "replay".to_owned()];
    let found = imports(&module, text);
    let expected = [
        (2, "rig"),
        (3, "protocol"),
        (3, "trajectory"),
        (5, "view"),
        (6, "stream"),
    ];
    let expected: Vec<(usize, String)> = expected
        .iter()
        .map(|(line, target)| (*line, target.to_string()))
        .collect();
    assert_eq!(found, expected);
    let offending: Vec<String> = found
        .iter()
        .filter_map(|(_, target)| offence("log", target))
        .collect();
    assert_eq!(offending.len(), 3, "{offending:?}");
    assert!(offending[0].contains("log -> trajectory"), "{offending:?}");
    assert!(offence("log", "unknown").unwrap().contains("not in LAYERS"));
}

/// Why `from` importing `target` breaks the order, if it does.
fn offence(from: &str, target: &str) -> Option<String> {
    if from == target {
        return None;
    }
    let rank = |name: &str| LAYERS.iter().position(|layer| *layer == name);
    match (rank(from), rank(target)) {
        (None, _) => Some(format!("module {from} is not in LAYERS")),
        (_, None) => Some(format!("{from} -> {target}: {target} is not in LAYERS")),
        (Some(a), Some(b)) if b < a => Some(format!(
            "{from} -> {target}: {target} is above {from} in the layer order"
        )),
        _ => None,
    }
}

/// The module a file under `src/` is, as its path from the crate root (`daemon/server.rs`
/// and `daemon/server/mod.rs` are both `daemon::server`); `None` for the library's root.
fn module_path(relative: &Path) -> Option<Vec<String>> {
    let mut parts: Vec<String> = relative
        .with_extension("")
        .iter()
        .map(|part| part.to_string_lossy().into_owned())
        .collect();
    if parts.last().is_some_and(|last| last == "mod") {
        parts.pop();
    }
    match parts.as_slice() {
        [root] if root == "lib" => None,
        [root] if root == "main" => Some(vec!["cli".to_owned()]),
        _ => Some(parts),
    }
}

/// Every top module that `text` (the file of module `module`) names before its test
/// module, with the line it is named on.
fn imports(module: &[String], text: &str) -> Vec<(usize, String)> {
    let code = code_only(text);
    let end = test_module_start(&code).unwrap_or(code.len());
    let code = &code[..end];
    let line_of = |at: usize| code[..at].iter().filter(|b| **b == b'\n').count() + 1;
    let mut found = Vec::new();
    let mut at = 0;
    while at < code.len() {
        if word_at(code, at, b"crate::") {
            let after = at + "crate::".len();
            for target in path_heads(code, after) {
                found.push((line_of(at), target));
            }
            at = after;
        } else if word_at(code, at, b"super::") {
            let mut supers = 0;
            let mut after = at;
            while code[after..].starts_with(b"super::") {
                supers += 1;
                after += "super::".len();
            }
            // `super` n times from `a::b::c` is `a::b::c` less n parts; at the crate root
            // the next name is a top module.
            if supers >= module.len() {
                for target in path_heads(code, after) {
                    found.push((line_of(at), target));
                }
            }
            at = after;
        } else {
            at += 1;
        }
    }
    found
}

/// Whether `word` starts at `at` and is not the tail of a longer name (`$crate::` counts).
fn word_at(code: &[u8], at: usize, word: &[u8]) -> bool {
    let ident = |b: u8| b.is_ascii_alphanumeric() || b == b'_';
    code[at..].starts_with(word) && (at == 0 || !ident(code[at - 1]))
}

/// The first names of the path at `at`: one name, or each item of a `{...}` group.
fn path_heads(code: &[u8], at: usize) -> Vec<String> {
    let name = |from: usize| -> String {
        code[from..]
            .iter()
            .take_while(|b| b.is_ascii_alphanumeric() || **b == b'_')
            .map(|b| *b as char)
            .collect()
    };
    if code.get(at) != Some(&b'{') {
        return vec![name(at)];
    }
    let mut heads = Vec::new();
    let mut depth = 0;
    let mut expecting = true;
    for (offset, byte) in code[at..].iter().enumerate() {
        match byte {
            b'{' => {
                depth += 1;
                expecting = depth == 1;
            }
            b'}' => {
                depth -= 1;
                if depth == 0 {
                    break;
                }
            }
            b',' if depth == 1 => expecting = true,
            b if expecting && (b.is_ascii_alphanumeric() || *b == b'_') => {
                heads.push(name(at + offset));
                expecting = false;
            }
            _ => {}
        }
    }
    heads
}

/// Where the file's `#[cfg(test)]` module starts (a `#[cfg(test)]` on an import is not it).
fn test_module_start(code: &[u8]) -> Option<usize> {
    let marker = b"#[cfg(test)]";
    (0..code.len()).find(|&at| {
        code[at..].starts_with(marker) && {
            let rest = &code[at + marker.len()..];
            let rest = &rest[rest.iter().take_while(|b| b.is_ascii_whitespace()).count()..];
            rest.starts_with(b"mod ") || rest.starts_with(b"pub mod ")
        }
    })
}

/// `text` with comments and string and char literals blanked (newlines kept, so offsets
/// and line numbers stay those of the file).
fn code_only(text: &str) -> Vec<u8> {
    let src = text.as_bytes();
    let mut out = src.to_vec();
    let mut at = 0;
    while at < src.len() {
        let end = match src[at] {
            b'/' if src.get(at + 1) == Some(&b'/') => {
                at + src[at..]
                    .iter()
                    .position(|b| *b == b'\n')
                    .unwrap_or(src.len() - at)
            }
            b'/' if src.get(at + 1) == Some(&b'*') => block_comment_end(src, at),
            b'r' if raw_string_start(src, at) => raw_string_end(src, at),
            b'"' => string_end(src, at),
            b'\'' => char_literal_end(text, at).unwrap_or(at + 1),
            _ => at + 1,
        };
        if end > at + 1 || matches!(src[at], b'"' | b'\'') {
            for byte in &mut out[at..end] {
                if *byte != b'\n' {
                    *byte = b' ';
                }
            }
        }
        at = end;
    }
    out
}

fn block_comment_end(src: &[u8], start: usize) -> usize {
    let mut depth = 0;
    let mut at = start;
    while at + 1 < src.len() {
        if src[at..].starts_with(b"/*") {
            depth += 1;
            at += 2;
        } else if src[at..].starts_with(b"*/") {
            depth -= 1;
            at += 2;
            if depth == 0 {
                return at;
            }
        } else {
            at += 1;
        }
    }
    src.len()
}

/// `r"`, `r#"`, `br"` ... not inside a longer name.
fn raw_string_start(src: &[u8], at: usize) -> bool {
    let ident = |b: u8| b.is_ascii_alphanumeric() || b == b'_';
    let before_ok = match at.checked_sub(1).map(|i| src[i]) {
        None => true,
        Some(b'b') => at < 2 || !ident(src[at - 2]),
        Some(b) => !ident(b),
    };
    let hashes = src[at + 1..].iter().take_while(|b| **b == b'#').count();
    before_ok && src.get(at + 1 + hashes) == Some(&b'"')
}

fn raw_string_end(src: &[u8], at: usize) -> usize {
    let hashes = src[at + 1..].iter().take_while(|b| **b == b'#').count();
    let mut closing = vec![b'"'];
    closing.extend(std::iter::repeat_n(b'#', hashes));
    let body = at + 2 + hashes;
    src[body..]
        .windows(closing.len())
        .position(|w| w == closing.as_slice())
        .map_or(src.len(), |p| body + p + closing.len())
}

fn string_end(src: &[u8], at: usize) -> usize {
    let mut i = at + 1;
    while i < src.len() {
        match src[i] {
            b'\\' => i += 2,
            b'"' => return i + 1,
            _ => i += 1,
        }
    }
    src.len()
}

/// The end of a char literal at `at` (`'a'`, `'\n'`, `'°'`); `None` for a lifetime (`'a`).
fn char_literal_end(text: &str, at: usize) -> Option<usize> {
    let src = text.as_bytes();
    if src.get(at + 1) == Some(&b'\\') {
        // The escaped character is never the closing quote (`'\''`).
        let close = src.get(at + 3..)?.iter().position(|b| *b == b'\'')?;
        return Some(at + 3 + close + 1);
    }
    let width = text.get(at + 1..)?.chars().next()?.len_utf8();
    (src.get(at + 1 + width) == Some(&b'\'')).then_some(at + 2 + width)
}
