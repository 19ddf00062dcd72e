//! The runs log and `--resume`: a benchmark cut short (a session's end, a crash, a reboot) goes
//! on where it stopped instead of training every run again.
//!
//! Every run with an output directory records the configuration it trains,
//! `bench-config.json`, beside its runs log (`runs.jsonl`, one line per finished training). A
//! resumed run reads both: it refuses a directory whose recorded configuration differs from its
//! own, keeps the trainings the log holds and trains the rest. Each training is deterministic
//! given its seed and the data (generated again from the data seed), so a kept run is the run
//! the resumed benchmark would have trained; only `threads`, how many trainings run side by
//! side, may change between the two invocations.

use std::path::Path;
use std::sync::Mutex;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Deserializer, Serialize};

use super::BenchConfig;

/// The configuration a run trains, beside its runs log.
pub const CONFIG_FILE: &str = "bench-config.json";

/// The configuration as recorded and compared: everything but `threads`, which changes no
/// result.
fn recorded(config: &BenchConfig) -> serde_json::Value {
    let mut value = serde_json::to_value(config).unwrap_or_default();
    if let Some(map) = value.as_object_mut() {
        map.remove("threads");
    }
    value
}

/// A fresh start: writes `bench-config.json` into `dir` and empties the runs log at `log`, so a
/// directory reused with `--force` never mixes two runs' trainings.
fn start(dir: &Path, log: &Path, config: &BenchConfig) -> Result<(), String> {
    let io = |e: std::io::Error| format!("{}: {e}", dir.display());
    std::fs::create_dir_all(dir).map_err(io)?;
    let text = serde_json::to_string_pretty(&recorded(config)).unwrap_or_default();
    std::fs::write(dir.join(CONFIG_FILE), text + "\n").map_err(io)?;
    std::fs::write(log, "").map_err(io)
}

/// With `config.resume`, the trainings the runs log already holds ([`kept_runs`]); otherwise
/// none, and a fresh log and recorded configuration ([`start`]). Nothing without a runs log.
pub fn earlier_runs<T: DeserializeOwned>(config: &BenchConfig) -> Result<Vec<T>, String> {
    let Some(log) = config.runs_log.as_deref() else { return Ok(Vec::new()) };
    let dir = log.parent().unwrap_or(Path::new("."));
    if config.resume {
        kept_runs(dir, log, config)
    } else {
        start(dir, log, config).map(|()| Vec::new())
    }
}

/// The trainings an earlier invocation finished, from the runs log at `log`, after checking
/// that `dir`'s recorded configuration is `config` (up to `threads`). A last line cut off
/// mid-write (the process killed while appending) is dropped with a warning and cut from the
/// log; any other line that does not parse is an error naming it.
fn kept_runs<T: DeserializeOwned>(
    dir: &Path,
    log: &Path,
    config: &BenchConfig,
) -> Result<Vec<T>, String> {
    let refuse = |why: String| format!("cannot resume in {}: {why}", dir.display());
    let text = std::fs::read_to_string(dir.join(CONFIG_FILE)).map_err(|e| {
        refuse(format!("no readable {CONFIG_FILE} ({e}); only a run that recorded its configuration can be resumed"))
    })?;
    let before: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| refuse(format!("{CONFIG_FILE}: {e}")))?;
    let now = recorded(config);
    let differing: Vec<String> = differing_keys(&before, &now)
        .into_iter()
        .filter(|key| !(key == "seeds" && more_seeds(&before, &now)))
        .collect();
    if !differing.is_empty() {
        return Err(refuse(format!(
            "its configuration differs in {} (run it with the same options, or start afresh \
             with --force)",
            differing.join(", ")
        )));
    }
    let lines = match std::fs::read_to_string(log) {
        Ok(lines) => lines,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
        Err(e) => return Err(refuse(format!("{}: {e}", log.display()))),
    };
    let runs = parse_log(&lines).map_err(refuse)?;
    if more_seeds(&before, &now) {
        // The next resume compares against the larger count this one trains.
        let text = serde_json::to_string_pretty(&now).unwrap_or_default();
        std::fs::write(dir.join(CONFIG_FILE), text + "\n").map_err(|e| refuse(e.to_string()))?;
    }
    if !lines.is_empty() && !lines.ends_with('\n') {
        // The cut-off line goes, so that the lines this run appends start on a line of their own.
        let whole = &lines[..lines.rfind('\n').map_or(0, |i| i + 1)];
        std::fs::write(log, whole).map_err(|e| refuse(format!("{}: {e}", log.display())))?;
    }
    Ok(runs)
}

/// The runs of a runs log's lines; see [`earlier_runs`] for the cut-off last line.
fn parse_log<T: DeserializeOwned>(text: &str) -> Result<Vec<T>, String> {
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    let mut runs = Vec::with_capacity(lines.len());
    for (i, line) in lines.iter().enumerate() {
        match serde_json::from_str::<T>(line) {
            Ok(run) => runs.push(run),
            Err(e) if i + 1 == lines.len() && !text.ends_with('\n') => {
                tracing::warn!(error = %e, "bench: the runs log's last line is cut off; training it again");
            }
            Err(e) => return Err(format!("runs.jsonl line {}: {e}", i + 1)),
        }
    }
    Ok(runs)
}

/// `runs.jsonl`: one JSON line per finished training, appended as it ends, so a benchmark cut
/// short still leaves its data (and [`earlier_runs`] can keep it).
pub struct RunsLog(Option<Mutex<std::fs::File>>);

impl RunsLog {
    /// Appends to the log at `path` (none: no log); a log that cannot be opened is warned about
    /// and the benchmark runs without one.
    pub fn open(path: Option<&Path>) -> RunsLog {
        let file = path.and_then(|path| {
            let opened = std::fs::create_dir_all(path.parent()?)
                .and_then(|()| std::fs::OpenOptions::new().create(true).append(true).open(path));
            opened
                .map_err(|e| tracing::warn!(path = %path.display(), error = %e, "no runs log"))
                .ok()
        });
        RunsLog(file.map(Mutex::new))
    }

    pub fn append(&self, run: &impl Serialize) {
        use std::io::Write;
        let Some(file) = &self.0 else { return };
        let line = serde_json::to_string(run).unwrap_or_default();
        let mut file = file.lock().unwrap_or_else(|p| p.into_inner());
        if let Err(e) = writeln!(file, "{line}") {
            tracing::warn!(error = %e, "could not append to the runs log");
        }
    }
}

/// Whether `now` asks for more training seeds than `before` recorded: a resumed run may add
/// seeds (each training depends on its own seed only, so the kept seeds are the ones the larger
/// run would train), never drop them (their trainings are in the log).
fn more_seeds(before: &serde_json::Value, now: &serde_json::Value) -> bool {
    let seeds = |config: &serde_json::Value| config.get("seeds").and_then(|n| n.as_u64());
    matches!((seeds(before), seeds(now)), (Some(b), Some(n)) if n > b)
}

/// The top-level keys whose values differ between two recorded configurations.
fn differing_keys(before: &serde_json::Value, now: &serde_json::Value) -> Vec<String> {
    let empty = serde_json::Map::new();
    let (a, b) = (before.as_object().unwrap_or(&empty), now.as_object().unwrap_or(&empty));
    let mut keys: Vec<String> =
        a.keys().chain(b.keys()).filter(|k| a.get(*k) != b.get(*k)).cloned().collect();
    keys.sort();
    keys.dedup();
    keys
}

/// serde_json writes a non-finite number as `null`: the diagnostics that are NaN when they do
/// not apply read back as NaN.
pub fn nan_if_null<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// [`nan_if_null`] for a map of scalars.
pub fn nan_if_null_values<'de, D: Deserializer<'de>>(
    d: D,
) -> Result<std::collections::BTreeMap<String, f64>, D::Error> {
    let map = std::collections::BTreeMap::<String, Option<f64>>::deserialize(d)?;
    Ok(map.into_iter().map(|(k, v)| (k, v.unwrap_or(f64::NAN))).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    type Line = serde_json::Value;

    #[test]
    fn a_configuration_differing_in_more_than_threads_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("runs.jsonl");
        let config = BenchConfig::quick();
        std::fs::write(&log, "a stale line of another run\n").unwrap();
        start(dir.path(), &log, &config).unwrap();
        assert_eq!(std::fs::read_to_string(&log).unwrap(), "", "a fresh start empties the log");
        let more_threads = BenchConfig { threads: 7, ..config.clone() };
        assert!(kept_runs::<Line>(dir.path(), &log, &more_threads).unwrap().is_empty());
        let other = BenchConfig { seeds: 1, iterations: 1, ..config };
        let refused = kept_runs::<Line>(dir.path(), &log, &other).unwrap_err();
        assert!(refused.contains("differs in iterations, seeds"), "{refused}");
    }

    /// A resume may add seeds, and records the larger count; it may not drop any.
    #[test]
    fn a_resume_may_add_seeds_but_not_drop_them() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("runs.jsonl");
        let config = BenchConfig { seeds: 3, ..BenchConfig::quick() };
        start(dir.path(), &log, &config).unwrap();
        std::fs::write(&log, "{\"seed\": 0}\n").unwrap();
        let five = BenchConfig { seeds: 5, ..config.clone() };
        assert_eq!(kept_runs::<Line>(dir.path(), &log, &five).unwrap().len(), 1);
        let recorded: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.path().join(CONFIG_FILE)).unwrap())
                .unwrap();
        assert_eq!(recorded["seeds"], 5, "the larger count is what a later resume compares with");
        let refused = kept_runs::<Line>(dir.path(), &log, &config).unwrap_err();
        assert!(refused.contains("differs in seeds"), "{refused}");
        let other = BenchConfig { seeds: 6, iterations: 1, ..config };
        let refused = kept_runs::<Line>(dir.path(), &log, &other).unwrap_err();
        assert!(refused.contains("differs in iterations (run"), "{refused}");
    }

    #[test]
    fn a_directory_without_a_recorded_configuration_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("runs.jsonl");
        let refused = kept_runs::<Line>(dir.path(), &log, &BenchConfig::quick()).unwrap_err();
        assert!(refused.contains("no readable bench-config.json"), "{refused}");
    }

    #[test]
    fn only_a_cut_off_last_line_is_dropped() {
        let whole = r#"{"env": "six-rooms"}"#;
        let runs = parse_log::<Line>(&format!("{whole}\n{{\"env\": \"six-r")).unwrap();
        assert_eq!(runs.len(), 1, "the whole line kept, the cut one dropped");
        let refused = parse_log::<Line>("{\"env\": \"six-r\n").unwrap_err();
        assert!(refused.starts_with("runs.jsonl line 1:"), "{refused}");
    }
}
