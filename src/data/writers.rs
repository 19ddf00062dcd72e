//! Writers in the upload formats, used by `safedice datagen` and the round-trip tests:
//! for a dataset a parser returned, `parse(write(d)) == d` (floats are written in their shortest
//! exactly-round-tripping decimal form). Action spaces: NPZ stores the box / count explicitly
//! (`action_low`/`action_high`/`action_n`); JSONL and CSV cannot, so their readers infer it
//! (see [`ActionSpace::infer_continuous`]) and a dataset whose declared space differs from the
//! inferred one comes back with the inferred one.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::Path;

use npyz::npz::NpzWriter;
use npyz::zip::write::FileOptions;
use npyz::zip::CompressionMethod;
use npyz::WriterBuilder;
use serde::Serialize;

use super::model::{ActionSpace, Actions, Dataset};

/// NPZ in the D4RL/DSRL flat layout (uncompressed, like `numpy.savez`), plus `episode_ids` and
/// the action space so the episodes and the space survive exactly.
pub fn write_npz(d: &Dataset, path: &Path) -> io::Result<()> {
    let n = d.len() as u64;
    let obs_shape = [n, d.obs_dim() as u64];
    let total_bytes = (d.observations().len() + d.next_observations().len()) as u64 * 4;
    // A fixed entry time (the zip epoch, 1980-01-01): two downloads of one dataset are the same
    // bytes, whatever second they were written in.
    let options = FileOptions::default()
        .last_modified_time(npyz::zip::DateTime::default())
        .compression_method(CompressionMethod::Stored)
        .large_file(total_bytes > u32::MAX as u64 / 2);
    let mut npz = NpzWriter::create(path)?;
    let mut array = |name: &str, shape: &[u64], values: &mut dyn Iterator<Item = f32>| {
        let mut w = npz.array::<f32>(name, options)?.default_dtype().shape(shape).begin_nd()?;
        w.extend(values)?;
        w.finish()
    };
    array("observations", &obs_shape, &mut d.observations().iter().copied())?;
    array("next_observations", &obs_shape, &mut d.next_observations().iter().copied())?;
    if let Actions::Continuous(a) = d.actions() {
        array("actions", &[n, d.action_space().width() as u64], &mut a.iter().copied())?;
    }
    for (name, column) in [("rewards", d.rewards()), ("costs", d.costs())] {
        if let Some(values) = column {
            array(name, &[n], &mut values.iter().copied())?;
        }
    }
    if let ActionSpace::Continuous { low, high, .. } = d.action_space() {
        array("action_low", &[low.len() as u64], &mut low.iter().copied())?;
        array("action_high", &[high.len() as u64], &mut high.iter().copied())?;
    }
    let mut ints = |name: &str, shape: &[u64], values: &mut dyn Iterator<Item = i64>| {
        let mut w = npz.array::<i64>(name, options)?.default_dtype().shape(shape).begin_nd()?;
        w.extend(values)?;
        w.finish()
    };
    if let Actions::Discrete(a) = d.actions() {
        ints("actions", &[n], &mut a.iter().map(|&x| x as i64))?;
    }
    if let ActionSpace::Discrete { n: count } = d.action_space() {
        ints("action_n", &[], &mut std::iter::once(*count as i64))?;
    }
    ints("episode_ids", &[n], &mut d.episode_ids().iter().map(|&x| x as i64))?;
    let ends = episode_ends(d);
    let mut flags = |name: &str, values: &mut dyn Iterator<Item = bool>| {
        let mut w = npz.array::<bool>(name, options)?.default_dtype().shape(&[n]).begin_nd()?;
        w.extend(values)?;
        w.finish()
    };
    flags("terminals", &mut d.terminals().iter().copied())?;
    // A timeout marks every episode end that is not terminal, so tools that split episodes at
    // `terminals | timeouts` (D4RL's convention) see the same episodes.
    flags("timeouts", &mut ends.iter().zip(d.terminals()).map(|(&end, &t)| end && !t))?;
    npz.zip_writer().finish()?;
    Ok(())
}

/// True at the last transition of each episode.
fn episode_ends(d: &Dataset) -> Vec<bool> {
    let mut ends = vec![false; d.len()];
    for r in d.episode_ranges() {
        ends[r.end - 1] = true;
    }
    ends
}

#[derive(Serialize)]
struct JsonRow<'a> {
    episode: u32,
    obs: &'a [f32],
    action: JsonAction<'a>,
    next_obs: &'a [f32],
    terminal: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    reward: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    cost: Option<f32>,
}

#[derive(Serialize)]
#[serde(untagged)]
enum JsonAction<'a> {
    Continuous(&'a [f32]),
    Discrete(u32),
}

/// JSONL, one transition per line, always with `next_obs` and `terminal`.
pub fn write_jsonl(d: &Dataset, path: &Path) -> io::Result<()> {
    let mut out = BufWriter::new(File::create(path)?);
    let width = d.action_space().width();
    for i in 0..d.len() {
        let action = match d.actions() {
            Actions::Continuous(a) => JsonAction::Continuous(&a[i * width..(i + 1) * width]),
            Actions::Discrete(a) => JsonAction::Discrete(a[i]),
        };
        let row = JsonRow {
            episode: d.episode_ids()[i],
            obs: d.obs(i),
            action,
            next_obs: d.next_obs(i),
            terminal: d.terminals()[i],
            reward: d.rewards().map(|r| r[i]),
            cost: d.costs().map(|c| c[i]),
        };
        serde_json::to_writer(&mut out, &row)?;
        out.write_all(b"\n")?;
    }
    out.flush()
}

/// CSV with the header `episode, obs_*, act_*|action, next_obs_*, terminal[, reward][, cost]`.
pub fn write_csv(d: &Dataset, path: &Path) -> io::Result<()> {
    let mut out = ::csv::Writer::from_writer(BufWriter::new(File::create(path)?));
    let mut header = vec!["episode".to_string()];
    header.extend((0..d.obs_dim()).map(|j| format!("obs_{j}")));
    match d.actions() {
        Actions::Continuous(_) => {
            header.extend((0..d.action_space().width()).map(|j| format!("act_{j}")))
        }
        Actions::Discrete(_) => header.push("action".into()),
    }
    header.extend((0..d.obs_dim()).map(|j| format!("next_obs_{j}")));
    header.push("terminal".into());
    header.extend(d.rewards().map(|_| "reward".to_string()));
    header.extend(d.costs().map(|_| "cost".to_string()));
    out.write_record(&header)?;

    let width = d.action_space().width();
    let mut record: Vec<String> = Vec::with_capacity(header.len());
    for i in 0..d.len() {
        record.clear();
        record.push(d.episode_ids()[i].to_string());
        // Rust's float Display is the shortest decimal that parses back to the same f32.
        record.extend(d.obs(i).iter().map(f32::to_string));
        match d.actions() {
            Actions::Continuous(a) => {
                record.extend(a[i * width..(i + 1) * width].iter().map(f32::to_string))
            }
            Actions::Discrete(a) => record.push(a[i].to_string()),
        }
        record.extend(d.next_obs(i).iter().map(f32::to_string));
        record.push(if d.terminals()[i] { "1" } else { "0" }.into());
        record.extend(d.rewards().map(|r| r[i].to_string()));
        record.extend(d.costs().map(|c| c[i].to_string()));
        out.write_record(&record)?;
    }
    out.flush()?;
    Ok(())
}
