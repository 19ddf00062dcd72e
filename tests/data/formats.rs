//! Upload parsers: each format's happy path, and each class of bad input rejected with its code
//! and a message naming the offending line / row / key.

use std::io::Write;
use std::path::{Path, PathBuf};

use npyz::npz::NpzWriter;
use npyz::WriterBuilder;
use safedice::data::{parse_file, ActionSpace, Actions, Dataset, DatasetParts, Format, ParseError};

struct Upload {
    _dir: tempfile::TempDir,
    path: PathBuf,
    name: String,
}

fn upload(name: &str, bytes: &[u8]) -> Upload {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::File::create(&path).unwrap().write_all(bytes).unwrap();
    Upload { _dir: dir, path, name: name.to_string() }
}

fn parse(name: &str, text: &str) -> Result<(Format, Dataset), ParseError> {
    let u = upload(name, text.as_bytes());
    parse_file(&u.path, &u.name)
}

fn ok(name: &str, text: &str) -> Dataset {
    match parse(name, text) {
        Ok((_, d)) => d,
        Err(e) => panic!("{name} rejected: {e}"),
    }
}

/// Asserts the error code and that the message contains every fragment.
fn rejected(result: Result<(Format, Dataset), ParseError>, code: &str, fragments: &[&str]) {
    let err = match result {
        Ok(_) => panic!("accepted, expected {code} mentioning {fragments:?}"),
        Err(e) => e,
    };
    assert_eq!(err.code, code, "message: {}", err.message);
    for f in fragments {
        assert!(err.message.contains(f), "message {:?} lacks {f:?}", err.message);
    }
}

// ---------------------------------------------------------------- JSONL

const JSONL_CONTINUOUS: &str = r#"{"episode": 7, "obs": [0, 1], "action": [0.5], "reward": 1, "cost": 0}
{"episode": 7, "obs": [1, 2], "action": [-0.5], "reward": 2, "cost": 1}
{"episode": 7, "obs": [2, 3], "action": [0.25], "terminal": true, "reward": 3, "cost": 0}
{"episode": 3, "obs": [5, 5], "action": [1.0], "next_obs": [6, 6], "reward": 4, "cost": 1}

"#;

#[test]
fn jsonl_continuous_fills_next_obs_from_the_next_row() {
    let (format, d) = parse("demos.jsonl", JSONL_CONTINUOUS).unwrap();
    assert_eq!(format, Format::Jsonl);
    assert_eq!(d.obs_dim(), 2);
    assert_eq!(d.observations(), vec![0., 1., 1., 2., 2., 3., 5., 5.]);
    // Rows 0 and 1 take the next row's obs; the terminal row 2 keeps its own obs.
    assert_eq!(d.next_observations(), vec![1., 2., 2., 3., 2., 3., 6., 6.]);
    assert_eq!(d.actions(), &Actions::Continuous(vec![0.5, -0.5, 0.25, 1.0]));
    assert_eq!(
        d.action_space(),
        &ActionSpace::Continuous { dim: 1, low: vec![-1.0], high: vec![1.0] }
    );
    assert_eq!(d.terminals(), vec![false, false, true, false]);
    assert_eq!(d.episode_ids(), vec![7, 7, 7, 3]);
    assert_eq!(d.rewards(), Some(&[1., 2., 3., 4.][..]));
    assert_eq!(d.costs(), Some(&[0., 1., 0., 1.][..]));
}

#[test]
fn jsonl_integer_actions_are_discrete() {
    let d = ok(
        "d.jsonl",
        "{\"episode\":0,\"obs\":[1.5],\"action\":2,\"next_obs\":[2],\"terminal\":0}\n\
         {\"episode\":0,\"obs\":[2],\"action\":0,\"next_obs\":[3],\"terminal\":1}\n",
    );
    assert_eq!(d.actions(), &Actions::Discrete(vec![2, 0]));
    assert_eq!(d.action_space(), &ActionSpace::Discrete { n: 3 });
    assert_eq!(d.terminals(), vec![false, true]);
    assert_eq!(d.rewards(), None);
}

#[test]
fn jsonl_is_detected_from_content_without_a_known_extension() {
    let (format, _) = parse("upload.bin", JSONL_CONTINUOUS).unwrap();
    assert_eq!(format, Format::Jsonl);
}

#[test]
fn jsonl_rejects_ragged_dimensions_with_the_line() {
    let text = JSONL_CONTINUOUS.replace("\"obs\": [1, 2]", "\"obs\": [1, 2, 3]");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 2", "`obs`", "3 values"]);
    let text = JSONL_CONTINUOUS.replace("[0.25]", "[0.25, 1]");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 3", "`action`", "ragged"]);
    let text = JSONL_CONTINUOUS.replace("\"next_obs\": [6, 6]", "\"next_obs\": [6]");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 4", "`next_obs`"]);
}

#[test]
fn jsonl_rejects_non_finite_values_with_the_line() {
    // Python's json.dumps writes NaN / Infinity, which are not JSON.
    let text = JSONL_CONTINUOUS.replace("[1, 2]", "[NaN, 2]");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 2", "NaN"]);
    // A finite decimal beyond f32's range is refused where it stands.
    let text = JSONL_CONTINUOUS.replace("[2, 3]", "[2, 1e39]");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 3", "`obs`[1]", "out of range"]);
    let text = JSONL_CONTINUOUS.replace("\"reward\": 2", "\"reward\": 1e40");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 2", "`reward`"]);
}

#[test]
fn jsonl_rejects_non_contiguous_episodes() {
    let text = format!(
        "{JSONL_CONTINUOUS}{}",
        r#"{"episode": 7, "obs": [5, 5], "action": [1.0], "next_obs": [6, 6], "reward": 4, "cost": 1}"#
    );
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 6", "episode 7", "contiguous"]);
}

#[test]
fn jsonl_rejects_mixed_discrete_and_continuous_actions() {
    let text = JSONL_CONTINUOUS.replace("[-0.5]", "1");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 2", "mixed", "line 1"]);
    let text = JSONL_CONTINUOUS.replace("[-0.5]", "0.5");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 2", "not an integer"]);
}

#[test]
fn jsonl_rejects_missing_fields_unknown_fields_and_garbage() {
    let text = JSONL_CONTINUOUS.replace("\"obs\": [1, 2], ", "");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 2", "missing field `obs`"]);
    let text = JSONL_CONTINUOUS.replace("\"next_obs\"", "\"next_ob\"");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 4", "unknown field `next_ob`"]);
    let text = JSONL_CONTINUOUS.replace("\"cost\": 1}", "\"cost\": 1");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 2"]);
    rejected(parse("d.jsonl", "[1, 2, 3]\n"), "invalid_dataset", &["JSON array"]);
}

#[test]
fn jsonl_rejects_an_unknown_successor_and_a_terminal_inside_an_episode() {
    let text = JSONL_CONTINUOUS.replace("\"terminal\": true, ", "");
    rejected(
        parse("d.jsonl", &text),
        "invalid_dataset",
        &["line 3", "episode 7", "no `next_obs`", "not terminal"],
    );
    let text = JSONL_CONTINUOUS.replace("[-0.5],", "[-0.5], \"terminal\": true,");
    rejected(
        parse("d.jsonl", &text),
        "invalid_dataset",
        &["line 3", "after its terminal", "line 2"],
    );
}

#[test]
fn jsonl_rejects_rewards_on_some_rows_only() {
    let text = JSONL_CONTINUOUS.replace(", \"reward\": 3", "");
    rejected(parse("d.jsonl", &text), "invalid_dataset", &["line 3", "`reward` is missing"]);
}

#[test]
fn jsonl_rejects_bad_discrete_actions() {
    let row = |a: &str| format!("{{\"episode\":0,\"obs\":[1],\"action\":{a},\"terminal\":true}}\n");
    rejected(parse("d.jsonl", &row("-1")), "invalid_dataset", &["line 1", "negative"]);
    rejected(parse("d.jsonl", &row("100000")), "invalid_dataset", &["line 1", "too large"]);
}

// ---------------------------------------------------------------- CSV

const CSV_CONTINUOUS: &str = "\
episode,obs_0,obs_1,act_0,act_1,terminal,reward,cost
0,0.5,1,0.1,-0.1,0,1,0
0,1.5,2,0.2,-0.2,1,1,1
1,9,9,0.3,-0.3,false,2,0
1,10,10,0.4,-0.4,true,2,0
";

#[test]
fn csv_continuous_with_derived_next_obs() {
    let (format, d) = parse("demos.csv", CSV_CONTINUOUS).unwrap();
    assert_eq!(format, Format::Csv);
    assert_eq!(d.obs_dim(), 2);
    assert_eq!(d.observations(), vec![0.5, 1., 1.5, 2., 9., 9., 10., 10.]);
    assert_eq!(d.next_observations(), vec![1.5, 2., 1.5, 2., 10., 10., 10., 10.]);
    assert_eq!(d.actions(), &Actions::Continuous(vec![0.1, -0.1, 0.2, -0.2, 0.3, -0.3, 0.4, -0.4]));
    assert_eq!(d.terminals(), vec![false, true, false, true]);
    assert_eq!(d.episode_ids(), vec![0, 0, 1, 1]);
    assert_eq!(d.costs(), Some(&[0., 1., 0., 0.][..]));
}

#[test]
fn csv_discrete_with_columns_in_any_order_and_next_obs() {
    let text = "\
next_obs_0,action,obs_0,episode
2,1,1,5
3,0,2,5
";
    let (format, d) = parse("upload", text).unwrap();
    assert_eq!(format, Format::Csv);
    assert_eq!(d.actions(), &Actions::Discrete(vec![1, 0]));
    assert_eq!(d.action_space(), &ActionSpace::Discrete { n: 2 });
    assert_eq!(d.next_observations(), vec![2., 3.]);
    assert_eq!(d.terminals(), vec![false, false]);
    assert_eq!(d.rewards(), None);
}

#[test]
fn crlf_line_endings_and_pandas_habits_are_accepted() {
    let crlf = JSONL_CONTINUOUS.replace('\n', "\r\n");
    assert_eq!(ok("d.jsonl", &crlf), ok("d.jsonl", JSONL_CONTINUOUS));
    let crlf = CSV_CONTINUOUS.replace('\n', "\r\n");
    assert_eq!(ok("d.csv", &crlf), ok("d.csv", CSV_CONTINUOUS));
    // pandas: True/False flags, integer columns written as 3.0 once they held a NaN.
    let d = ok("d.csv", "episode,obs_0,action,terminal\n3.0,1,2.0,False\n3.0,2,0,True\n");
    assert_eq!(d.episode_ids(), vec![3, 3]);
    assert_eq!(d.actions(), &Actions::Discrete(vec![2, 0]));
    assert_eq!(d.terminals(), vec![false, true]);
    let text = format!(",{}", CSV_CONTINUOUS.replace('\n', "\n0,"));
    rejected(parse("d.csv", text.trim_end_matches("0,")), "invalid_dataset", &["index=False"]);
}

#[test]
fn csv_rejects_ragged_rows_and_bad_cells_with_line_and_column() {
    let text = CSV_CONTINUOUS.replace("1.5,2,0.2", "1.5,0.2");
    rejected(parse("d.csv", &text), "invalid_dataset", &["line 3", "7 fields", "header has 8"]);
    let text = CSV_CONTINUOUS.replace("1.5,2,", "nan,2,");
    rejected(parse("d.csv", &text), "invalid_dataset", &["line 3", "`obs_0`", "finite"]);
    let text = CSV_CONTINUOUS.replace("9,9,0.3", "9,x,0.3");
    rejected(
        parse("d.csv", &text),
        "invalid_dataset",
        &["line 4", "`obs_1`", "`x` is not a number"],
    );
    let text = CSV_CONTINUOUS.replace("9,9,0.3", "9,,0.3");
    rejected(parse("d.csv", &text), "invalid_dataset", &["line 4", "`obs_1`", "empty"]);
    let text = CSV_CONTINUOUS.replace(",true,", ",maybe,");
    rejected(parse("d.csv", &text), "invalid_dataset", &["line 5", "`terminal`"]);
}

#[test]
fn csv_rejects_bad_headers() {
    let text = CSV_CONTINUOUS.replace("episode,", "ep,");
    rejected(parse("d.csv", &text), "invalid_dataset", &["header", "unknown column `ep`"]);
    let text = CSV_CONTINUOUS.replace("obs_1,", "obs_2,");
    rejected(parse("d.csv", &text), "invalid_dataset", &["header", "`obs_1` is missing"]);
    let text = CSV_CONTINUOUS.replace(",cost", ",action");
    rejected(parse("d.csv", &text), "invalid_dataset", &["mixed discrete and continuous"]);
    let text = CSV_CONTINUOUS.replace("reward,", "reward,reward,").replace(",1,0\n", ",1,1,0\n");
    rejected(parse("d.csv", &text), "invalid_dataset", &["`reward` appears twice"]);
}

#[test]
fn csv_rejects_non_contiguous_episodes_and_fractional_discrete_actions() {
    let text = format!("{CSV_CONTINUOUS}0,1,1,0.1,0.1,1,0,0\n");
    rejected(parse("d.csv", &text), "invalid_dataset", &["line 6", "episode 0", "contiguous"]);
    let text = "episode,obs_0,action,terminal\n0,1,1.5,1\n";
    rejected(parse("d.csv", text), "invalid_dataset", &["line 2", "`action`", "integer"]);
}

// ---------------------------------------------------------------- detection, empty, unknown

#[test]
fn format_names_round_trip_through_str_and_serde() {
    for f in [Format::Jsonl, Format::Csv, Format::Npz, Format::Hdf5] {
        assert_eq!(f.as_str().parse::<Format>().unwrap(), f);
        assert_eq!(serde_json::to_string(&f).unwrap(), format!("\"{f}\""));
    }
    assert_eq!("parquet".parse::<Format>().unwrap_err().code, "unknown_format");
}

#[test]
fn empty_and_unknown_files() {
    rejected(parse("d.jsonl", ""), "empty_dataset", &["d.jsonl"]);
    rejected(parse("d.csv", " \n\n"), "empty_dataset", &[]);
    rejected(parse("d.csv", "episode,obs_0,action\n"), "empty_dataset", &[]);
    rejected(parse("notes.txt", "hello world\n"), "unknown_format", &["notes.txt", ".npz"]);
    let gz = upload("d.jsonl.gz", b"\x1f\x8b\x08\x00rest");
    rejected(parse_file(&gz.path, &gz.name), "unknown_format", &["gzip"]);
}

#[test]
fn names_that_contradict_the_content_are_rejected() {
    rejected(parse("d.npz", "episode,obs_0\n"), "invalid_dataset", &["d.npz", "not a zip"]);
    rejected(parse("d.csv", JSONL_CONTINUOUS), "invalid_dataset", &["rename it to .jsonl"]);
    rejected(parse("d.h5", "{}"), "invalid_dataset", &["HDF5 signature"]);
}

// ---------------------------------------------------------------- NPZ

/// Builds an NPZ with arrays of any dtype, as numpy would write them.
struct Npz {
    writer: NpzWriter<std::io::BufWriter<std::fs::File>>,
}

impl Npz {
    fn create(path: &Path) -> Npz {
        Npz { writer: NpzWriter::create(path).unwrap() }
    }

    fn array<T: npyz::AutoSerialize + Clone>(mut self, name: &str, shape: &[u64], v: &[T]) -> Self {
        let options = npyz::zip::write::FileOptions::default()
            .compression_method(npyz::zip::CompressionMethod::Deflated);
        let mut w = self
            .writer
            .array::<T>(name, options)
            .unwrap()
            .default_dtype()
            .shape(shape)
            .begin_nd()
            .unwrap();
        w.extend(v.iter().cloned()).unwrap();
        w.finish().unwrap();
        self
    }

    fn finish(mut self) {
        self.writer.zip_writer().finish().unwrap();
    }
}

/// A D4RL-like archive (float64 observations, bool terminals, uint8 timeouts) without the keys
/// in `skip`, plus whatever `edit` adds (replacements for skipped keys, extra keys).
fn npz_upload(
    skip: &[&str],
    edit: impl FnOnce(Npz) -> Npz,
) -> Result<(Format, Dataset), ParseError> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.npz");
    let keep = |name: &str| !skip.contains(&name);
    let mut npz = Npz::create(&path);
    if keep("observations") {
        npz = npz.array::<f64>("observations", &[5, 2], &[0., 0., 1., 1., 2., 2., 3., 3., 4., 4.]);
    }
    if keep("next_observations") {
        let next = [1., 1., 2., 2., 3., 3., 4., 4., 5., 5.];
        npz = npz.array::<f64>("next_observations", &[5, 2], &next);
    }
    if keep("actions") {
        npz = npz.array::<f32>("actions", &[5, 1], &[0.1, 0.2, 0.3, 0.4, 0.5]);
    }
    if keep("terminals") {
        npz = npz.array::<bool>("terminals", &[5], &[false, true, false, false, false]);
    }
    if keep("timeouts") {
        npz = npz.array::<u8>("timeouts", &[5], &[0, 0, 0, 1, 0]);
    }
    if keep("costs") {
        npz = npz.array::<f64>("costs", &[5], &[0., 1., 0., 0., 1.]);
    }
    edit(npz).finish();
    parse_file(&path, "d.npz")
}

#[test]
fn npz_flat_layout_splits_episodes_at_terminals_and_timeouts() {
    let (format, d) = npz_upload(&[], |n| n).unwrap();
    assert_eq!(format, Format::Npz);
    assert_eq!(d.obs_dim(), 2);
    assert_eq!(d.episode_ids(), vec![0, 0, 1, 1, 2]);
    assert_eq!(d.terminals(), vec![false, true, false, false, false]);
    assert_eq!(d.actions(), &Actions::Continuous(vec![0.1, 0.2, 0.3, 0.4, 0.5]));
    assert_eq!(d.next_observations()[8..], [5., 5.]);
    assert_eq!(d.rewards(), None);
    assert_eq!(d.costs(), Some(&[0., 1., 0., 0., 1.][..]));
}

#[test]
fn npz_integer_actions_float_terminals_and_omnisafe_names() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("omnisafe.npz");
    Npz::create(&path)
        .array::<f32>("obs", &[3, 1], &[0., 1., 2.])
        .array::<f32>("next_obs", &[3, 1], &[1., 2., 3.])
        .array::<i64>("action", &[3], &[0, 3, 1])
        .array::<f32>("done", &[3], &[0., 0., 1.])
        .array::<f32>("cost", &[3], &[0., 1., 0.])
        .finish();
    let (_, d) = parse_file(&path, "omnisafe.npz").unwrap();
    assert_eq!(d.actions(), &Actions::Discrete(vec![0, 3, 1]));
    assert_eq!(d.action_space(), &ActionSpace::Discrete { n: 4 });
    assert_eq!(d.terminals(), vec![false, false, true]);
    assert_eq!(d.episode_ids(), vec![0, 0, 0]);
    assert_eq!(d.costs(), Some(&[0., 1., 0.][..]));
}

#[test]
fn npz_rejects_missing_keys() {
    for key in ["observations", "actions", "terminals"] {
        let fragment = format!("missing required key `{key}`");
        rejected(npz_upload(&[key], |n| n), "invalid_dataset", &[&fragment]);
    }
}

/// Without `next_observations` each row's successor is the next row of its episode; the rows
/// that end an episode at a timeout (3) or at the end of the file (4) have none and are dropped,
/// the terminal one (1) keeps its own observation, and the dataset says so.
#[test]
fn npz_without_next_observations_derives_them_within_each_episode() {
    let (_, d) = npz_upload(&["next_observations"], |n| n).unwrap();
    assert_eq!(d.observations(), [0., 0., 1., 1., 2., 2.]);
    assert_eq!(d.next_observations(), [1., 1., 1., 1., 3., 3.]);
    assert_eq!(d.terminals(), [false, true, false]);
    assert_eq!(d.episode_ids(), [0, 0, 1]);
    assert_eq!(d.costs(), Some(&[0., 1., 0.][..]));
    assert_eq!(d.actions(), &Actions::Continuous(vec![0.1, 0.2, 0.3]));
    assert_eq!(d.warnings().len(), 1);
    assert!(
        d.warnings()[0].contains("2 of the 5 transitions end an episode"),
        "{:?}",
        d.warnings()
    );

    // Every row the last of an episode that is not terminal: nothing to derive from.
    let only_timeouts = npz_upload(&["next_observations", "terminals", "timeouts"], |n| {
        n.array::<bool>("terminals", &[5], &[false; 5]).array::<u8>("timeouts", &[5], &[1; 5])
    });
    rejected(only_timeouts, "empty_dataset", &["no transition's next observation"]);
}

/// Neither terminals nor timeouts nor episode ids mark an end: one long episode, said so.
#[test]
fn a_file_with_no_episode_ends_is_one_episode_with_a_warning() {
    let (_, d) =
        npz_upload(&["terminals", "timeouts"], |n| n.array::<bool>("terminals", &[5], &[false; 5]))
            .unwrap();
    assert_eq!(d.episode_ids(), [0; 5]);
    assert!(
        d.warnings()[0].starts_with("no transition is marked terminal or timeout"),
        "{:?}",
        d.warnings()
    );
}

#[test]
fn npz_rejects_wrong_dtypes_shapes_and_values() {
    let reject = |skip: &[&str], edit: fn(Npz) -> Npz, fragments: &[&str]| {
        rejected(npz_upload(skip, edit), "invalid_dataset", fragments)
    };
    reject(
        &["observations"],
        |n| n.array::<i32>("observations", &[5, 2], &[0; 10]),
        &["`observations`", "integer"],
    );
    reject(
        &["observations"],
        |n| n.array::<f32>("observations", &[5, 2, 1], &[0.; 10]),
        &["`observations`", "shape [5, 2, 1]"],
    );
    reject(
        &["next_observations"],
        |n| n.array::<f32>("next_observations", &[4, 2], &[0.; 8]),
        &["`next_observations`", "(4, 2)"],
    );
    reject(
        &["actions"],
        |n| n.array::<i64>("actions", &[5, 2], &[0; 10]),
        &["`actions`", "mixed discrete and continuous"],
    );
    reject(
        &["actions"],
        |n| n.array::<i64>("actions", &[5], &[0, 1, -1, 0, 0]),
        &["`actions`", "row 2"],
    );
    reject(
        &["terminals"],
        |n| n.array::<f32>("terminals", &[5], &[0., 0.5, 0., 0., 0.]),
        &["`terminals`", "row 1", "0 or 1"],
    );
    reject(
        &["costs"],
        |n| n.array::<f64>("costs", &[5], &[0., 0., f64::NAN, 0., 0.]),
        &["`costs`", "row 2", "NaN"],
    );
    reject(
        &["observations"],
        |n| n.array::<f64>("observations", &[5, 2], &[1e300; 10]),
        &["`observations`", "row 0", "inf"],
    );
    reject(&[], |n| n.array::<i32>("init_obs", &[2, 3], &[0; 6]), &["`init_obs`", "integer"]);
    reject(&[], |n| n.array::<f32>("init_obs", &[2, 3], &[0.; 6]), &["`init_obs`", "3 columns"]);
    reject(
        &[],
        |n| n.array::<i64>("episode_ids", &[5], &[0, 0, 0, 1, 1]),
        &["`episode_ids`", "row 1", "continues"],
    );
    reject(
        &[],
        |n| n.array::<i64>("episode_ids", &[5], &[0, 0, 1, 1, 0]),
        &["episode 0", "not contiguous"],
    );
}

#[test]
fn npz_rejects_truncated_and_empty_archives() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("full.npz");
    writers_fixture(&path);
    let bytes = std::fs::read(&path).unwrap();
    for cut in [bytes.len() / 2, bytes.len() - 10, 100] {
        let u = upload("cut.npz", &bytes[..cut]);
        rejected(parse_file(&u.path, &u.name), "invalid_dataset", &["truncated or corrupt"]);
    }
    // A flipped byte inside the stored data fails the zip CRC check, naming the key.
    let mut corrupt = bytes.clone();
    corrupt[200] ^= 0xff;
    let u = upload("crc.npz", &corrupt);
    rejected(parse_file(&u.path, &u.name), "invalid_dataset", &["key `observations`"]);
    rejected(
        npz_upload(
            &["observations", "next_observations", "actions", "terminals", "timeouts", "costs"],
            |n| {
                n.array::<f32>("observations", &[0, 3], &[])
                    .array::<f32>("next_observations", &[0, 3], &[])
                    .array::<f32>("actions", &[0, 1], &[])
                    .array::<bool>("terminals", &[0], &[])
            },
        ),
        "empty_dataset",
        &["`observations` has no rows"],
    );
}

fn writers_fixture(path: &Path) {
    let d = Dataset::new(DatasetParts {
        obs_dim: 3,
        action_space: ActionSpace::Continuous { dim: 1, low: vec![-1.0], high: vec![1.0] },
        observations: (0..60).map(|x| x as f32).collect(),
        actions: Actions::Continuous(vec![0.5; 20]),
        next_observations: (3..63).map(|x| x as f32).collect(),
        terminals: (0..20).map(|i| i == 19).collect(),
        episode_ids: vec![0; 20],
        rewards: None,
        costs: None,
    })
    .unwrap();
    safedice::data::write_npz(&d, path).unwrap();
}

// ---------------------------------------------------------------- NPZ written by numpy itself

fn fixture(name: &str) -> (Format, Dataset) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name);
    parse_file(&path, name).unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// tests/fixtures/make_npz_fixtures.py: compressed, Fortran-ordered float64 observations, bool
/// terminals, uint8 timeouts, a big-endian float64 cost column, an ignored `infos/qpos` key.
#[test]
fn numpy_savez_compressed_d4rl_layout() {
    let (format, d) = fixture("d4rl_like.npz");
    assert_eq!(format, Format::Npz);
    let obs: Vec<f32> = (0..18).map(|x| x as f32 / 4.0).collect();
    assert_eq!(d.observations(), obs);
    assert_eq!(d.next_observations(), obs.iter().map(|x| x + 0.25).collect::<Vec<_>>());
    let Actions::Continuous(actions) = d.actions() else { panic!("continuous expected") };
    let linspace = (0..12).map(|i| (-1.0 + i as f64 * 2.0 / 11.0) as f32);
    assert!(actions.iter().zip(linspace).all(|(a, b)| (a - b).abs() < 1e-6), "{actions:?}");
    assert_eq!(d.action_space().width(), 2);
    assert_eq!(d.terminals(), vec![false, false, true, false, false, false]);
    assert_eq!(d.episode_ids(), vec![0, 0, 0, 1, 1, 2]);
    assert_eq!(d.rewards(), Some(&[1.0; 6][..]));
    assert_eq!(d.costs(), Some(&[0., 1., 0., 1., 1., 0.][..]));
}

#[test]
fn numpy_savez_discrete_omnisafe_names() {
    let (_, d) = fixture("discrete.npz");
    assert_eq!(d.actions(), &Actions::Discrete(vec![0, 2, 1, 1, 0, 2]));
    assert_eq!(d.action_space(), &ActionSpace::Discrete { n: 3 });
    assert_eq!(d.terminals(), vec![false, false, false, true, false, true]);
    assert_eq!(d.episode_ids(), vec![0, 0, 0, 0, 1, 1]);
    assert_eq!(d.obs_dim(), 3);
}

/// The NPZ writer stamps no wall-clock time in its entries: a dataset written twice, seconds
/// apart (zip times have a 2 s resolution), is the same bytes, so two downloads match.
#[test]
fn an_npz_written_twice_seconds_apart_is_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let (first, second) = (dir.path().join("a.npz"), dir.path().join("b.npz"));
    writers_fixture(&first);
    std::thread::sleep(std::time::Duration::from_millis(2100));
    writers_fixture(&second);
    assert_eq!(std::fs::read(first).unwrap(), std::fs::read(second).unwrap());
}
