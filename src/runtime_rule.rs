//! The rule the layout keeps: nothing in the runtime (the stages, `core`, `pipeline`, `service`,
//! `store`, `http`) prints, shows progress, reads the environment or imports the offline code
//! (`research`, `cli`, `config`). This test reads the runtime's sources and fails naming the file
//! and line that breaks it. Test code (`#[cfg(test)]` modules, `tests.rs` files) is exempt: tests
//! may read the shared data through `config` and train small models through `research`.

use std::path::{Path, PathBuf};

/// The runtime: every file under these folders, and these files.
const RUNTIME: [&str; 11] =
    ["core", "detect", "landmarks", "morph", "embed", "recognize", "quality.rs", "pipeline.rs", "service", "store", "http"];

/// What the runtime must not contain, with the reason shown on failure.
const FORBIDDEN: [(&str, &str); 9] = [
    ("println!", "prints"),
    ("eprintln!", "prints"),
    ("print!(", "prints"),
    ("eprint!(", "prints"),
    ("dbg!(", "prints"),
    ("indicatif", "shows progress"),
    ("std::env::var", "reads the environment"),
    ("std::env::args", "reads the environment"),
    ("env::var", "reads the environment"),
];

/// The offline modules the runtime must not import (as `crate::<module>`), with the reason.
const OFFLINE: [(&str, &str); 3] = [
    ("research", "imports research code"),
    ("cli", "imports the command line"),
    ("config", "reads the settings (the environment); take plain values instead"),
];

/// The forbidden patterns `line` holds, each with its reason.
fn violations(line: &str) -> Vec<(String, &'static str)> {
    let imports = OFFLINE.iter().map(|(module, reason)| (format!("crate::{module}"), *reason));
    FORBIDDEN.iter().map(|(p, r)| (p.to_string(), *r)).chain(imports).filter(|(p, _)| line.contains(p.as_str())).collect()
}

fn rust_files(path: &Path, out: &mut Vec<PathBuf>) {
    if path.is_dir() {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(path).unwrap().map(|e| e.unwrap().path()).collect();
        entries.sort();
        for entry in entries {
            rust_files(&entry, out);
        }
    } else if path.extension().is_some_and(|e| e == "rs") && path.file_name().is_some_and(|n| n != "tests.rs") {
        out.push(path.to_path_buf());
    }
}

/// The lines of `source` outside comments and test code: a `#[cfg(test)]` item is skipped (a
/// `mod tests;` declaration, or an inline module up to the `}` at its own indentation).
fn runtime_lines(source: &str) -> Vec<(usize, &str)> {
    let lines: Vec<&str> = source.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i].trim();
        if line == "#[cfg(test)]" {
            let item = lines.get(i + 1).copied().unwrap_or("");
            if item.trim().ends_with(';') {
                i += 2;
                continue;
            }
            let indent = &item[..item.len() - item.trim_start().len()];
            let end = lines[i + 1..].iter().position(|l| *l == format!("{indent}}}")).map_or(lines.len(), |k| i + 1 + k);
            i = end + 1;
            continue;
        }
        if !line.starts_with("//") {
            out.push((i + 1, lines[i]));
        }
        i += 1;
    }
    out
}

#[test]
fn the_runtime_neither_prints_nor_reads_the_environment_nor_imports_research_code() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    for entry in RUNTIME {
        let path = src.join(entry);
        assert!(path.exists(), "{} is listed as runtime but does not exist", path.display());
        rust_files(&path, &mut files);
    }
    assert!(files.len() > 30, "only {} runtime files found", files.len());
    let mut broken = Vec::new();
    for file in &files {
        let source = std::fs::read_to_string(file).unwrap();
        for (number, line) in runtime_lines(&source) {
            for (pattern, reason) in violations(line) {
                broken.push(format!("{}:{number}: {reason} ({pattern}): {}", file.strip_prefix(&src).unwrap().display(), line.trim()));
            }
        }
    }
    assert!(
        broken.is_empty(),
        "the runtime must not print, show progress, read the environment or import research code:\n{}",
        broken.join("\n")
    );
}

/// Research code reports through the writer and the `Progress` its caller hands down; only the CLI
/// prints.
#[test]
fn research_code_does_not_print() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src.join("research"), &mut files);
    let mut broken = Vec::new();
    for file in &files {
        let source = std::fs::read_to_string(file).unwrap();
        for (number, line) in runtime_lines(&source) {
            for (pattern, reason) in FORBIDDEN.iter().filter(|(_, reason)| *reason == "prints" || *reason == "shows progress") {
                if line.contains(pattern) {
                    broken.push(format!("{}:{number}: {reason} ({pattern}): {}", file.strip_prefix(&src).unwrap().display(), line.trim()));
                }
            }
        }
    }
    assert!(broken.is_empty(), "research code must not print or draw progress bars (the CLI does):\n{}", broken.join("\n"));
}

#[test]
fn the_scan_finds_what_it_forbids() {
    let source = "fn a() {\n    // println!(\"in a comment\")\n    eprintln!(\"x\");\n}\n#[cfg(test)]\nmod tests;\nuse crate::research::dataset;\n#[cfg(test)]\nmod t {\n    println!(\"test\");\n}\nfn b() { print!(\"after the tests\"); }\n";
    let lines: Vec<usize> = runtime_lines(source).into_iter().filter(|(_, l)| !violations(l).is_empty()).map(|(n, _)| n).collect();
    assert_eq!(lines, [3, 7, 12]);
}
