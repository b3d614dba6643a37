//! The user guide's commands, run: every fenced block of `docs/guide/*.md` whose info string is
//! `sh run` is executed, in order, page by page, so the guide cannot rot. A page's blocks share
//! one scratch folder (a later block uses what an earlier one wrote) and find `subsurf` on the
//! `PATH` (the binary this test target was built with). Blocks marked plain `sh` are not run: they
//! need hardware, Blender, a browser or minutes of release-mode time.
//!
//! The commands run on the simulated rig, the simulated camera and the built-in objects at small
//! sizes, so the whole guide takes well under a minute in a debug build.
use std::path::{Path, PathBuf};
use std::process::Command;

/// The guide's pages, in name order.
fn pages() -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/guide");
    let mut out: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    out.sort();
    out
}

/// The runnable blocks of a Markdown text: the lines between a "```sh run" fence and the next
/// closing fence, with the line number of the fence.
fn runnable(md: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut open: Option<(usize, String)> = None;
    for (i, line) in md.lines().enumerate() {
        let t = line.trim();
        match &mut open {
            None if t.starts_with("```") => {
                let info: Vec<&str> = t.trim_start_matches('`').split_whitespace().collect();
                // Another block (start 0) is skipped to its end.
                let run = info.first() == Some(&"sh") && info.contains(&"run");
                open = Some((if run { i + 1 } else { 0 }, String::new()));
            }
            Some((start, body)) if t.starts_with("```") => {
                if *start > 0 {
                    out.push((*start, std::mem::take(body)));
                }
                open = None;
            }
            Some((_, body)) => {
                body.push_str(line);
                body.push('\n');
            }
            None => {}
        }
    }
    out
}

#[test]
fn the_extractor_takes_only_blocks_marked_runnable() {
    let md = "text\n```sh run\nsubsurf plan\n```\n```sh\nsubsurf flash\n```\n```json\n{}\n```\n\
              ```sh run\na\nb\n```\n";
    let blocks = runnable(md);
    assert_eq!(
        blocks,
        [
            (2, "subsurf plan\n".to_string()),
            (11, "a\nb\n".to_string())
        ]
    );
}

#[test]
fn every_runnable_command_of_the_guide_runs() {
    let exe = PathBuf::from(env!("CARGO_BIN_EXE_subsurf"));
    let bin_dir = exe.parent().unwrap().to_path_buf();
    let path = std::env::join_paths(std::iter::once(bin_dir).chain(std::env::split_paths(
        &std::env::var_os("PATH").unwrap_or_default(),
    )))
    .unwrap();
    let pages = pages();
    assert!(pages.len() >= 7, "the guide has {} pages", pages.len());
    for page in pages.iter().filter(|p| !p.ends_with("README.md")) {
        let md = std::fs::read_to_string(page).unwrap();
        // A task's page opens with its commands: the first thing after the title is a block.
        let first = md.lines().skip(1).find(|l| !l.trim().is_empty());
        assert!(
            first.is_some_and(|l| l.starts_with("```sh")),
            "{} does not open with its commands",
            page.display()
        );
        assert!(!runnable(&md).is_empty(), "{} runs nothing", page.display());
    }
    for page in &pages {
        let md = std::fs::read_to_string(page).unwrap();
        let scratch = tempfile::tempdir().unwrap();
        for (line, body) in runnable(&md) {
            let script = format!("set -euo pipefail\n{body}");
            let o = Command::new("bash")
                .arg("-c")
                .arg(&script)
                .current_dir(scratch.path())
                .env("PATH", &path)
                .output()
                .unwrap();
            assert!(
                o.status.success(),
                "{}:{line}: the block failed ({}):\n{body}\n--- stdout\n{}\n--- stderr\n{}",
                page.display(),
                o.status,
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            );
        }
    }
}
