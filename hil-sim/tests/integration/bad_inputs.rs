//! Bad input files never crash `hil-sim`: every scenario, plant and calibration file below (the
//! cases found by hand, then a fixed budget of random mutations of good files) ends in exit 0 or
//! in exit 1 with one `hil-sim: ...` line that names the file at fault; never a panic (101), an
//! abort (134), a signal or a hang.
//!
//! The binary runs as a child process, so that an abort or a stack overflow is seen as what it
//! is. `BAD_INPUT_CASES` sets the number of random cases (default 500, a few seconds).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

const PLANT: &str = include_str!("../../presets/paper-rig.toml");
/// A short scenario (about 0.5 s simulated) with a reversal and a retarget.
const SCENARIO: &str = "name = \"short\"
start_mm = 100.0

[[move]]
to_mm = 108.0
velocity_mm_s = 100.0
accel_mm_s2 = 2000.0
retarget_after_ms = 60

[[move]]
to_mm = 96.0
velocity_mm_s = 80.0
accel_mm_s2 = 3000.0
dwell_ms = 20
";

/// Wall-clock limit of one child: far above a good run (well under a second).
const CHILD_LIMIT: Duration = Duration::from_secs(60);

fn scratch(name: &str) -> PathBuf {
    // Under `target/`, not the system's temporary directory: the calibration made once per
    // run is never removed (it lives in a `static`), and `cargo clean` takes it.
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("bad-inputs-{name}"));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A good calibration directory, made once by `hil-sim calibrate`.
fn good_calibration() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = scratch("calibration");
        let out = run(&["calibrate", "--out", d.to_str().unwrap()]);
        assert_eq!(out.code, Some(0), "calibrate: {}", out.stderr);
        d
    })
}

struct Outcome {
    code: Option<i32>,
    stderr: String,
}

fn run(args: &[&str]) -> Outcome {
    run_to(args, Stdio::null())
}

/// [`run`] with standard output on `stdout`.
fn run_to(args: &[&str], stdout: Stdio) -> Outcome {
    let mut child = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(args)
        .stdin(Stdio::null())
        .stdout(stdout)
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn hil-sim");
    let mut err = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = std::io::Read::read_to_string(&mut err, &mut s);
        s
    });
    Outcome {
        code: wait_within_limit(&mut child, args),
        stderr: reader.join().unwrap(),
    }
}

/// The exit code of `hil-sim args` with both standard output and standard error into pipes
/// whose readers have gone (`2>&1 | head`).
fn run_into_closed_pipes(args: &[&str]) -> Option<i32> {
    let mut child = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(args)
        .stdin(Stdio::null())
        .stdout(pipe_without_reader())
        .stderr(pipe_without_reader())
        .spawn()
        .expect("spawn hil-sim");
    wait_within_limit(&mut child, args)
}

fn wait_within_limit(child: &mut std::process::Child, args: &[&str]) -> Option<i32> {
    let start = Instant::now();
    let code = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status.code();
        }
        if start.elapsed() > CHILD_LIMIT {
            let _ = child.kill();
            let _ = child.wait();
            panic!("hil-sim {args:?}: no exit after {CHILD_LIMIT:?} (a hang)");
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    code
}

/// The verdict every input must get: success, or a clean refusal naming one of `files`.
fn check(what: &str, out: &Outcome, files: &[&str]) -> Result<(), String> {
    let last = out.stderr.lines().last().unwrap_or("");
    if out.stderr.contains("panicked") || out.stderr.contains("RUST_BACKTRACE") {
        return Err(format!("{what}: a panic:\n{}", out.stderr));
    }
    match out.code {
        Some(0) => Ok(()),
        Some(1) if last.starts_with("hil-sim: ") && files.iter().any(|f| last.contains(f)) => {
            Ok(())
        }
        Some(1) => Err(format!("{what}: the error names none of {files:?}: {last}")),
        other => Err(format!(
            "{what}: exit {other:?} (expected 0 or 1):\n{}",
            out.stderr
        )),
    }
}

/// `hil-sim run` of `scenario` with the calibration in `cal`, its table thrown away.
fn run_scenario(scenario: &str, cal: &str) -> Outcome {
    run(&[
        "run",
        "--scenario",
        scenario,
        "--calibration",
        cal,
        "--out",
        "/dev/null",
    ])
}

/// A refusal: exit 1 and one `hil-sim: ` line that names `file` (see [`check`]) and says each
/// of `says`.
fn refused(file: &str, out: &Outcome, says: &[&str]) -> Result<(), String> {
    let last = out.stderr.lines().last().unwrap_or("");
    if out.code != Some(1) {
        return Err(format!("{file}: exit {:?}, expected 1: {last}", out.code));
    }
    check(file, out, &[file])?;
    match says.iter().find(|m| !last.contains(*m)) {
        Some(m) => Err(format!("{file}: the message lacks `{m}`: {last}")),
        None => Ok(()),
    }
}

/// A scenario file with `moves` in place of the short scenario's.
fn scenario_with(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p.to_str().unwrap().to_string()
}

/// A pipe whose reader has already gone: every write to it fails with a broken pipe.
fn pipe_without_reader() -> Stdio {
    let (reader, writer) = std::io::pipe().expect("pipe");
    drop(reader);
    writer.into()
}

#[test]
fn output_to_a_closed_pipe_or_a_full_disk_is_no_panic() {
    let dir = scratch("stdout");
    let cal = good_calibration().to_str().unwrap().to_string();
    let scenario = scenario_with(&dir, "short.toml", SCENARIO);
    let evaluate = ["evaluate", "--scenario", &scenario, "--calibration", &cal];
    let csv = ["run", "--scenario", &scenario, "--calibration", &cal];
    // `| head`: the reader took what it wanted; quiet, and a success.
    for args in [&evaluate[..], &csv[..]] {
        let out = run_to(args, pipe_without_reader());
        assert_eq!(
            out.code,
            Some(0),
            "{args:?} into a closed pipe: {}",
            out.stderr
        );
        assert!(!out.stderr.contains("panicked"), "{args:?}: {}", out.stderr);
    }
    // A full disk loses output: said on stderr, and a failure.
    for args in [&evaluate[..], &csv[..]] {
        let Ok(full) = std::fs::OpenOptions::new().write(true).open("/dev/full") else {
            break;
        };
        let out = run_to(args, full.into());
        assert_eq!(out.code, Some(1), "{args:?} into /dev/full: {}", out.stderr);
        assert!(out.stderr.contains("standard output: "), "{}", out.stderr);
        assert!(!out.stderr.contains("panicked"), "{}", out.stderr);
    }
    // Standard error closed too: a refusal still exits 1 and a good run 0, with no panic (101)
    // where the message or the progress could not be written.
    let missing = ["evaluate", "--scenario", "/nonexistent/scenario.toml"];
    assert_eq!(run_into_closed_pipes(&missing), Some(1));
    assert_eq!(run_into_closed_pipes(&evaluate), Some(0));
}

#[test]
fn the_reported_inputs_are_refused_by_file_move_and_field() {
    let dir = scratch("reported");
    let cal = good_calibration().to_str().unwrap().to_string();
    let one = |to: &str, v: &str, a: &str, extra: &str| {
        format!(
            "name = \"x\"\nstart_mm = 20.0\n[[move]]\nto_mm = {to}\nvelocity_mm_s = {v}\naccel_mm_s2 = {a}\n{extra}"
        )
    };
    // 250,000 moves (14.5 MB, under the 16 MiB a text input may have) take longer than a run may.
    let mut many = String::from("name = \"many\"\nstart_mm = 10.0\n");
    for i in 0..250_000 {
        many += &format!(
            "[[move]]\nto_mm = {}\nvelocity_mm_s = 250\naccel_mm_s2 = 5000\n",
            10 + i % 2
        );
    }
    // (file name, text, what the message must also say)
    let cases: Vec<(&str, String, &[&str])> = vec![
        (
            "slow.toml",
            one("200", "0.0001", "100", ""),
            &["move 1", "velocity_mm_s"],
        ),
        (
            "tiny_accel.toml",
            one("200", "10", "1e-6", ""),
            &["move 1", "accel_mm_s2"],
        ),
        (
            "dwell.toml",
            one("200", "10", "100", "dwell_ms = 4294967295\n"),
            &["move 1", "dwell_ms"],
        ),
        (
            "vel_1e-300.toml",
            one("200", "1e-300", "100", ""),
            &["move 1", "velocity_mm_s"],
        ),
        (
            "far.toml",
            one("2000", "1000", "100", ""),
            &["move 1", "to_mm"],
        ),
        (
            "too_fast.toml",
            one("200", "1000", "100", ""),
            &["move 1", "velocity_mm_s"],
        ),
        (
            "too_steep.toml",
            one("200", "100", "40000", ""),
            &["move 1", "accel_mm_s2"],
        ),
        (
            "last_retarget.toml",
            one("200", "100", "1000", "retarget_after_ms = 50\n"),
            &["move 1", "retarget_after_ms"],
        ),
        ("huge.toml", many.repeat(2), &["larger than 16 MiB"]),
        ("many.toml", many, &["move", "accel_mm_s2"]),
    ];
    let mut failures = Vec::new();
    for (name, text, also) in &cases {
        let s = scenario_with(&dir, name, text);
        if let Err(e) = refused(name, &run_scenario(&s, &cal), also) {
            failures.push(e);
        }
    }

    // The drive's own limits are accepted exactly as the drive takes them: the travel's ends,
    // and a speed that rounds to the limit in whole um/s.
    let ends = scenario_with(
        &dir,
        "ends.toml",
        "name = \"ends\"\nstart_mm = 100.0\n[[move]]\nto_mm = 300.0\nvelocity_mm_s = 250.0004\n\
         accel_mm_s2 = 5000.0\n[[move]]\nto_mm = 0.0\nvelocity_mm_s = 250.0\naccel_mm_s2 = 5000.0\n",
    );
    let out = run(&[
        "run",
        "--scenario",
        &ends,
        "--calibration",
        &cal,
        "--out",
        "/dev/null",
    ]);
    if out.code != Some(0) {
        failures.push(format!("ends.toml: exit {:?}: {}", out.code, out.stderr));
    }

    // A plant whose travel starts above the scenario's start, and above the calibration
    // scenarios' (20 mm).
    let high = dir.join("high_travel.toml");
    std::fs::write(
        &high,
        PLANT.replace("travel_min_m = -0.01", "travel_min_m = 0.030"),
    )
    .unwrap();
    assert!(std::fs::read_to_string(&high)
        .unwrap()
        .contains("travel_min_m = 0.030"));
    let h = high.to_str().unwrap();
    let s = scenario_with(&dir, "start20.toml", &one("200", "100", "1000", ""));
    for args in [
        vec![
            "run",
            "--scenario",
            &s,
            "--plant",
            h,
            "--calibration",
            &cal,
            "--out",
            "/dev/null",
        ],
        vec![
            "calibrate",
            "--plant",
            h,
            "--out",
            dir.join("never").to_str().unwrap(),
        ],
    ] {
        let out = run(&args);
        let last = out.stderr.lines().last().unwrap_or("").to_string();
        if out.code != Some(1) || !last.contains("high_travel.toml") || !last.contains("start_mm") {
            failures.push(format!("{args:?}: exit {:?}: {last}", out.code));
        }
    }

    // Calibration files: an edited model section, a NaN, an unknown field, a short blob.
    for (name, edit) in [
        ("edited", ("h_mm = ", "h_mm = 0.5 # ")),
        ("nan", ("backlash_um = ", "backlash_um = nan # ")),
        ("unknown", ("[backlash]", "[backlash]\nslack_um = 3.0")),
        ("slip", ("half_gap_um = ", "half_gap_um = 100.0 # ")),
    ] {
        let d = dir.join(name);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::copy(
            good_calibration().join("calibration.bin"),
            d.join("calibration.bin"),
        )
        .unwrap();
        let text = std::fs::read_to_string(good_calibration().join("calibration.toml")).unwrap();
        assert!(text.contains(edit.0), "{name}: {}", edit.0);
        std::fs::write(d.join("calibration.toml"), text.replacen(edit.0, edit.1, 1)).unwrap();
        let out = run(&[
            "run",
            "--scenario",
            &s,
            "--calibration",
            d.to_str().unwrap(),
            "--out",
            "/dev/null",
        ]);
        let last = out.stderr.lines().last().unwrap_or("").to_string();
        if out.code != Some(1) || !last.contains("calibration.toml") {
            failures.push(format!("calibration {name}: exit {:?}: {last}", out.code));
        }
    }
    let d = dir.join("short_blob");
    std::fs::create_dir_all(&d).unwrap();
    let bin = std::fs::read(good_calibration().join("calibration.bin")).unwrap();
    std::fs::write(d.join("calibration.bin"), &bin[..bin.len() / 2]).unwrap();
    std::fs::copy(
        good_calibration().join("calibration.toml"),
        d.join("calibration.toml"),
    )
    .unwrap();
    let out = run(&[
        "run",
        "--scenario",
        &s,
        "--calibration",
        d.to_str().unwrap(),
        "--out",
        "/dev/null",
    ]);
    let last = out.stderr.lines().last().unwrap_or("").to_string();
    if out.code != Some(1) || !last.contains("calibration.bin") {
        failures.push(format!("short blob: exit {:?}: {last}", out.code));
    }
    let _ = std::fs::remove_dir_all(&dir);
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Values that break careless parsers and range checks.
const NASTY: &[&str] = &[
    "0",
    "-1",
    "1e-300",
    "1e300",
    "nan",
    "inf",
    "-inf",
    "4294967295",
    "-4294967296",
    "18446744073709551616",
    "\"text\"",
    "[]",
    "true",
    "0.5",
    "1e9",
    "-0.0",
    "{}",
    "",
];

/// One mutation of a text file.
#[derive(Clone, Debug)]
enum TextEdit {
    /// The value of the n-th `key = value` line becomes a nasty one.
    Value(usize, usize),
    /// The n-th line goes.
    Delete(usize),
    /// The n-th line appears twice.
    Duplicate(usize),
    /// The file ends after this fraction of its bytes.
    Truncate(f64),
    /// Bytes of junk at a fraction of the file.
    Junk(f64, Vec<u8>),
}

fn text_edit() -> impl Strategy<Value = TextEdit> {
    prop_oneof![
        4 => (any::<usize>(), 0..NASTY.len()).prop_map(|(i, v)| TextEdit::Value(i, v)),
        1 => any::<usize>().prop_map(TextEdit::Delete),
        1 => any::<usize>().prop_map(TextEdit::Duplicate),
        1 => (0.0..1.0f64).prop_map(TextEdit::Truncate),
        1 => ((0.0..1.0f64), proptest::collection::vec(any::<u8>(), 1..8))
            .prop_map(|(f, b)| TextEdit::Junk(f, b)),
    ]
}

fn apply(text: &str, edit: &TextEdit) -> Vec<u8> {
    let lines: Vec<&str> = text.lines().collect();
    let pick = |i: usize| i % lines.len().max(1);
    let mut out: Vec<String> = lines.iter().map(|l| l.to_string()).collect();
    match edit {
        TextEdit::Value(i, v) => {
            let keyed: Vec<usize> = (0..lines.len())
                .filter(|&k| lines[k].contains('=') && !lines[k].trim_start().starts_with('#'))
                .collect();
            if let Some(&k) = keyed.get(i % keyed.len().max(1)) {
                let key = lines[k].split('=').next().unwrap();
                out[k] = format!("{key}= {}", NASTY[*v]);
            }
        }
        TextEdit::Delete(i) => {
            if !out.is_empty() {
                out.remove(pick(*i));
            }
        }
        TextEdit::Duplicate(i) => {
            if !out.is_empty() {
                let l = out[pick(*i)].clone();
                out.insert(pick(*i), l);
            }
        }
        TextEdit::Truncate(f) => {
            let b = text.as_bytes();
            return b[..(b.len() as f64 * f) as usize].to_vec();
        }
        TextEdit::Junk(f, junk) => {
            let mut b = text.as_bytes().to_vec();
            let at = (b.len() as f64 * f) as usize;
            b.splice(at..at, junk.iter().copied());
            return b;
        }
    }
    (out.join("\n") + "\n").into_bytes()
}

/// Which file a case breaks, and how.
#[derive(Clone, Debug)]
enum Case {
    Scenario(TextEdit),
    Plant(TextEdit),
    CalibrationToml(TextEdit),
    /// Byte `at` (a fraction of the blob) xor `x`, or the blob cut at `at` when `x` is 0.
    CalibrationBin(f64, u8),
}

fn case() -> impl Strategy<Value = Case> {
    prop_oneof![
        3 => text_edit().prop_map(Case::Scenario),
        3 => text_edit().prop_map(Case::Plant),
        1 => text_edit().prop_map(Case::CalibrationToml),
        1 => ((0.0..1.0f64), any::<u8>()).prop_map(|(a, x)| Case::CalibrationBin(a, x)),
    ]
}

#[test]
fn mutated_scenario_plant_and_calibration_files_never_crash() {
    let cases: u32 = std::env::var("BAD_INPUT_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(500);
    let good = good_calibration();
    let dir = scratch("fuzz");
    let config = Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    };
    // A fixed seed: CI runs the same cases every time.
    let mut runner =
        TestRunner::new_with_rng(config, TestRng::deterministic_rng(RngAlgorithm::ChaCha));
    let result = runner.run(&case(), |c| {
        let (s, p, cal) = (dir.join("s.toml"), dir.join("p.toml"), dir.join("cal"));
        std::fs::create_dir_all(&cal).unwrap();
        let toml = std::fs::read_to_string(good.join("calibration.toml")).unwrap();
        let mut bin = std::fs::read(good.join("calibration.bin")).unwrap();
        let (mut s_text, mut p_text, mut c_text) = (
            SCENARIO.as_bytes().to_vec(),
            PLANT.as_bytes().to_vec(),
            toml.as_bytes().to_vec(),
        );
        match &c {
            Case::Scenario(e) => s_text = apply(SCENARIO, e),
            Case::Plant(e) => p_text = apply(PLANT, e),
            Case::CalibrationToml(e) => c_text = apply(&toml, e),
            Case::CalibrationBin(at, x) => {
                let i = ((bin.len() as f64 * at) as usize).min(bin.len() - 1);
                if *x == 0 {
                    bin.truncate(i);
                } else {
                    bin[i] ^= x;
                }
            }
        }
        std::fs::write(&s, s_text).unwrap();
        std::fs::write(&p, p_text).unwrap();
        std::fs::write(cal.join("calibration.toml"), c_text).unwrap();
        std::fs::write(cal.join("calibration.bin"), bin).unwrap();
        let out = run(&[
            "run",
            "--scenario",
            s.to_str().unwrap(),
            "--plant",
            p.to_str().unwrap(),
            "--calibration",
            cal.to_str().unwrap(),
            "--out",
            "/dev/null",
        ]);
        check(
            &format!("{c:?}"),
            &out,
            &["s.toml", "p.toml", "calibration.toml", "calibration.bin"],
        )
        .map_err(TestCaseError::fail)
    });
    let _ = std::fs::remove_dir_all(&dir);
    if let Err(e) = result {
        panic!("{e}");
    }
}

/// `generalise --plot` into a directory that does not exist, or onto a directory, is refused by
/// the option before minutes of measuring: nothing is printed (the tables come before the
/// picture).
#[test]
fn a_picture_that_cannot_be_written_is_refused_before_measuring() {
    let dir = scratch("plot");
    let missing = dir.join("missing").join("g.png");
    let tables = dir.join("tables.md");
    for target in [missing.to_str().unwrap(), dir.to_str().unwrap()] {
        let stdout = std::fs::File::create(&tables).unwrap();
        let out = run_to(
            &["generalise", "--no-variants", "--plot", target],
            Stdio::from(stdout),
        );
        assert_eq!(out.code, Some(1), "{}", out.stderr);
        let last = out.stderr.lines().last().unwrap_or("");
        assert!(last.contains("--plot") && last.contains(target), "{last}");
        assert_eq!(std::fs::read(&tables).unwrap().len(), 0, "measured first");
    }
}

/// Numbers on the command line that would overflow a wall-clock `Duration` are refused by the
/// option: the virtual drive's pace and `qemu-run`'s time-out.
#[test]
fn durations_beyond_reach_are_refused_by_option() {
    let dir = scratch("durations");
    let storage = dir.join("flash.bin");
    for speed in ["1e-300", "0.001", "-1", "NaN", "inf"] {
        let out = run(&[
            "virtual-drive",
            "--storage",
            storage.to_str().unwrap(),
            "--elf",
            "/dev/null",
            &format!("--speed={speed}"),
        ]);
        assert_eq!(out.code, Some(1), "--speed {speed}: {}", out.stderr);
        let last = out.stderr.lines().last().unwrap_or("");
        assert!(
            last.contains("--speed") && last.contains("0.01 to 1000"),
            "{last}"
        );
        assert!(!storage.exists(), "--speed {speed}: storage made");
    }
    for timeout in ["1e20", "0", "NaN"] {
        let out = Command::new(env!("CARGO_BIN_EXE_qemu-run"))
            .args([&format!("--timeout={timeout}"), "/dev/null"])
            .output()
            .expect("spawn qemu-run");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "--timeout {timeout}: {err}");
        assert!(
            err.contains("--timeout") && !err.contains("panicked"),
            "{err}"
        );
    }
}

/// `report --out DIR` where the report or its trace would land on a directory is refused by
/// the option and the file before the run: nothing else is written into `DIR`. A `DIR` that
/// does not exist yet is no error (the main job writes into a fresh `out/report`).
#[test]
fn a_report_whose_files_cannot_be_written_is_refused_before_the_run() {
    let dir = scratch("report_out");
    let cal = good_calibration().to_str().unwrap().to_string();
    for file in ["report.md", "repeatability.csv"] {
        let out_dir = dir.join(file.replace('.', "_"));
        std::fs::create_dir_all(out_dir.join(file)).unwrap();
        let out = run(&[
            "report",
            "--scenario",
            "repeatability",
            "--calibration",
            &cal,
            "--out",
            out_dir.to_str().unwrap(),
        ]);
        assert_eq!(out.code, Some(1), "{file}: {}", out.stderr);
        let last = out.stderr.lines().last().unwrap_or("");
        assert!(
            last.contains("--out") && last.contains(file) && last.contains("is a directory"),
            "{last}"
        );
        let written: Vec<_> = std::fs::read_dir(&out_dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(written, [std::ffi::OsString::from(file)], "{file}");
    }
    // A directory that does not exist yet passes (the report makes it): the run goes on to the
    // next input, here a calibration that does not exist, and leaves no `--out` behind.
    let fresh = dir.join("fresh").join("report");
    let missing = dir.join("no_calibration");
    let out = run(&[
        "report",
        "--scenario",
        "repeatability",
        "--calibration",
        missing.to_str().unwrap(),
        "--out",
        fresh.to_str().unwrap(),
    ]);
    let last = out.stderr.lines().last().unwrap_or("");
    assert_eq!(out.code, Some(1), "{}", out.stderr);
    assert!(
        last.contains("no_calibration") && !last.contains("--out"),
        "{last}"
    );
    assert!(!dir.join("fresh").exists(), "--out left behind");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Inputs that passed the checks and then hung, ran into nonsense or blamed another file: each
/// is now refused by its file and field before anything runs, or runs to its end.
#[test]
fn plants_specials_and_slow_starts_are_refused_by_field_or_run() {
    let dir = scratch("audit");
    let cal = good_calibration().to_str().unwrap().to_string();
    let fig = "fig18";
    let mut failures = Vec::new();
    // (file, the line replaced, its replacement, what the message must say)
    let plants: [(&str, &str, &str, &[&str]); 5] = [
        (
            "lines1.toml",
            "lines = 2000",
            "lines = 1",
            &["encoder.lines 1", "cannot run it"],
        ),
        (
            "ratio.toml",
            "ratio = 23.7222",
            "ratio = 9000.0",
            &["gearbox.ratio 9000", "cannot run it"],
        ),
        (
            "runout.toml",
            "eccentricity_m = 6.0e-6",
            "eccentricity_m = 0.02",
            &["pulley.eccentricity_m"],
        ),
        (
            "light.toml",
            "mass_kg = 2.5",
            "mass_kg = 1e-6",
            &["carriage.mass_kg"],
        ),
        (
            "noise.toml",
            "noise_sd_m = 0.1e-6",
            "noise_sd_m = 1e300",
            &["scale.noise_sd_m", "1e300 must"],
        ),
    ];
    for (name, from, to, says) in plants {
        assert!(PLANT.contains(from), "{name}: {from}");
        let p = dir.join(name);
        std::fs::write(&p, PLANT.replacen(from, to, 1)).unwrap();
        let p = p.to_str().unwrap();
        for args in [
            vec![
                "run",
                "--scenario",
                fig,
                "--plant",
                p,
                "--calibration",
                &cal,
                "--out",
                "/dev/null",
            ],
            vec!["faults", "--plant", p],
        ] {
            let out = run(&args);
            let last = out.stderr.lines().last().unwrap_or("").to_string();
            if out.code != Some(1) || !last.starts_with(&format!("hil-sim: {p}: ")) {
                failures.push(format!("{args:?}: exit {:?}: {last}", out.code));
            } else if let Some(m) = says.iter().find(|m| !last.contains(*m)) {
                failures.push(format!("{name}: the message lacks `{m}`: {last}"));
            }
        }
    }
    // Scenarios: a start inside the plant's travel but outside the drive's, and a retarget
    // wait of 49 days (it ran until its time-out).
    let head = "name = \"x\"\nstart_mm = 100.0\n";
    let mv = |to: &str, extra: &str| {
        format!("[[move]]\nto_mm = {to}\nvelocity_mm_s = 10.0\naccel_mm_s2 = 100.0\n{extra}")
    };
    for (name, text, says) in [
        (
            "start350.toml",
            format!("name = \"x\"\nstart_mm = 350.0\n{}", mv("100", "")),
            ["start_mm", "the drive's travel"],
        ),
        (
            "wait.toml",
            format!(
                "{head}{}{}",
                mv("110", "retarget_after_ms = 4294967295\n"),
                mv("100", "")
            ),
            ["move 1", "retarget_after_ms"],
        ),
    ] {
        let s = scenario_with(&dir, name, &text);
        if let Err(e) = refused(name, &run_scenario(&s, &cal), &says) {
            failures.push(e);
        }
    }
    // A device or a directory where a file is read: refused by name (/dev/zero was read until
    // memory ran out).
    for path in ["/dev/zero", dir.to_str().unwrap()] {
        if let Err(e) = refused(path, &run_scenario(path, &cal), &[]) {
            failures.push(e);
        }
    }
    // A start beyond the travel but within the drive's margin (300 + 5 mm) still runs.
    let margin = scenario_with(
        &dir,
        "margin.toml",
        &format!("name = \"m\"\nstart_mm = 302.0\n{}", mv("299", "")),
    );
    let out = run_scenario(&margin, &cal);
    if out.code != Some(0) {
        failures.push(format!("margin.toml: exit {:?}: {}", out.code, out.stderr));
    }
    // A slow first move to where the scenario starts: homing leaves the drive off `start_mm`
    // by the transmission error, a way the time-out did not count.
    let slow = scenario_with(
        &dir,
        "slow_start.toml",
        &format!("{head}[[move]]\nto_mm = 100.0\nvelocity_mm_s = 0.01\naccel_mm_s2 = 1.0\n"),
    );
    let out = run_scenario(&slow, &cal);
    if out.code != Some(0) {
        failures.push(format!(
            "slow_start.toml: exit {:?}: {}",
            out.code, out.stderr
        ));
    }
    let _ = std::fs::remove_dir_all(&dir);
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
