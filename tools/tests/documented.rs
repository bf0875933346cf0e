//! The documented `leangate eval` commands against the real sequences of `../shared/data`, as a
//! reader runs them: every sequence a command names is there or the text beside it says how to
//! get it, every real sequence there is read and gated whole, and the figures the docs print for
//! them are what the eval produces now. Skipped, saying so, when `../shared/data` is absent.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

#[allow(dead_code)]
mod common;
use common::eval_json;

#[path = "../../tests/common/paths.rs"]
#[allow(dead_code)]
mod paths;
use paths::shared_data;

/// The repository root (the tools crate is one level down).
fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// The documents a reader runs commands from.
const DOCS: [&str; 8] = [
    "README.md",
    "docs/element.md",
    "docs/python.md",
    "docs/tools.md",
    "docs/reconstruction.md",
    "docs/results.md",
    "models/README.md",
    "training/README.md",
];

/// Paragraphs (blank-line separated) of a document.
fn paragraphs(text: &str) -> Vec<String> {
    text.split("\n\n").map(str::to_string).collect()
}

/// The names of `../shared/data` sequences a paragraph's `leangate eval` commands use, written
/// `../shared/data/NAME` or, after `S=../shared/data;`, `$S/NAME`.
fn shared_names(paragraph: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    if !(paragraph.contains("leangate eval") || paragraph.contains("$B eval")) {
        return names;
    }
    let uses_s = paragraph.contains("S=../shared/data");
    for (prefix, on) in [("../shared/data/", true), ("$S/", uses_s)] {
        if !on {
            continue;
        }
        for (at, _) in paragraph.match_indices(prefix) {
            let rest = &paragraph[at + prefix.len()..];
            let name: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_' || *c == '-')
                .collect();
            // The data README itself, and placeholders such as `SEQ`, are not sequences.
            let placeholder = name.chars().all(|c| !c.is_ascii_lowercase());
            if !name.is_empty() && name != "README" && !placeholder {
                names.insert(name);
            }
        }
    }
    names
}

/// Every documented eval command names data a reader has, or says right beside it how to make
/// it (the importers that rebuild the sequences `../shared/data` does not carry). The README's
/// cross-sequence command named three absent sequences with the way to get them a page away.
#[test]
fn documented_eval_commands_name_data_that_exists_or_say_how_to_get_it() {
    let Some(data) = shared_data("") else {
        eprintln!("SKIPPED: ../shared/data is absent");
        return;
    };
    let mut checked = 0;
    let mut missing = Vec::new();
    for doc in DOCS {
        let text = std::fs::read_to_string(repo().join(doc)).unwrap();
        for p in paragraphs(&text) {
            for name in shared_names(&p) {
                checked += 1;
                if data.join(&name).exists() {
                    continue;
                }
                let says_how = p.contains("training.import_") || p.contains("training/README.md");
                if !says_how {
                    missing.push(format!("{doc}: `{name}` in: {}", p.trim()));
                }
            }
        }
    }
    assert!(checked >= 3, "found only {checked} documented sequences");
    assert!(
        missing.is_empty(),
        "documented commands name sequences absent from {} with no word on how to get them:\n{}",
        data.display(),
        missing.join("\n\n")
    );
}

/// The row of the model card's table "Every real sequence of `../shared/data` in one run" for
/// `name`: `| name | frames | oracle | kept / late / min S | ...`, as (frames, oracle, kept, late).
fn card_row(name: &str) -> Option<(u64, Option<u64>, u64, Option<u64>)> {
    let card = std::fs::read_to_string(repo().join("models/README.md")).unwrap();
    let start = card.find("Every real sequence of `../shared/data` in one run")?;
    let row = card[start..]
        .lines()
        .find(|l| l.starts_with(&format!("| {name} |")) || l.starts_with(&format!("| {name} (")))?;
    let cells: Vec<&str> = row.split('|').map(str::trim).collect();
    let num = |s: &str| s.replace(',', "").parse::<u64>().ok();
    let frames = num(cells[2])?;
    let oracle = num(cells[3]);
    let mut kept_late = cells[4].split('/').map(str::trim);
    let kept = kept_late
        .next()
        .and_then(|s| num(s.split_whitespace().next()?))?;
    let late = kept_late.next().and_then(num);
    Some((frames, oracle, kept, late))
}

/// Every real sequence in `../shared/data` with a frame list is read whole and gated by the
/// documented command, with every colour frame (none dropped for want of ground truth where the
/// data README says each row is associated), and where the model card prints its figures the
/// eval produces them now. TUM fr1_rpy's depth.txt repeats a row 44 times (two colour frames
/// sharing their nearest depth image): it used to be refused at line 343.
#[test]
fn eval_runs_on_every_real_sequence_and_reproduces_the_documented_figures() {
    let Some(data) = shared_data("") else {
        eprintln!("SKIPPED: ../shared/data is absent");
        return;
    };
    let mut seqs: Vec<PathBuf> = std::fs::read_dir(&data)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("rgb.txt").is_file())
        .collect();
    seqs.sort();
    assert!(
        !seqs.is_empty(),
        "no sequence with rgb.txt in {}",
        data.display()
    );
    let mut compared = 0;
    for seq in &seqs {
        let name = seq.file_name().unwrap().to_string_lossy().into_owned();
        let rows = std::fs::read_to_string(seq.join("rgb.txt"))
            .unwrap()
            .lines()
            .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
            .count() as u64;
        let r = eval_json(seq, &[]);
        eprintln!(
            "{name}: {} frames, model kept {}, oracle {}, late {}",
            r["frames"],
            r["policies"]["model"]["kept"],
            r["policies"]["oracle"]["kept"],
            r["policies"]["model"]["late_keeps"]
        );
        assert_eq!(
            r["frames"].as_u64(),
            Some(rows),
            "{name}: every colour frame gated"
        );
        if let Some((frames, oracle, kept, late)) = card_row(&name) {
            compared += 1;
            let m = &r["policies"]["model"];
            assert_eq!(r["frames"].as_u64(), Some(frames), "{name}: frames");
            assert_eq!(m["kept"].as_u64(), Some(kept), "{name}: the card's kept");
            if let Some(o) = oracle {
                assert_eq!(
                    r["policies"]["oracle"]["kept"].as_u64(),
                    Some(o),
                    "{name}: oracle"
                );
            }
            if let Some(l) = late {
                assert_eq!(m["late_keeps"].as_u64(), Some(l), "{name}: late keeps");
            }
        }
    }
    assert!(
        compared >= 1,
        "no sequence of {} has a row in the model card",
        data.display()
    );
}
