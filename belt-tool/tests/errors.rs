//! beltctl's error paths against fakes: the binary as a user runs it, its port a pseudo-terminal
//! whose other end is a fake drive (or nothing at all).

mod common;

use std::time::Duration;

use belt_link::Request;
use common::{beltctl, beltctl_into, pty, serve, text, FakeDrive, Faults};

const LIMIT: Duration = Duration::from_secs(20);

/// Short timeouts keep the run short; three tries as by default.
fn args<'a>(port: &'a str, rest: &[&'a str]) -> Vec<&'a str> {
    let mut v = vec!["--port", port, "--timeout-ms", "60", "--retries", "3"];
    v.extend_from_slice(rest);
    v
}

fn assert_clean_failure(out: &std::process::Output) -> String {
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "stderr: {err}");
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(err.lines().count(), 1, "one line: {err}");
    err
}

#[test]
fn a_port_that_does_not_exist_is_named() {
    let (out, _) = beltctl(&["--port", "/dev/ttyNOSUCH9", "status"], LIMIT);
    let err = assert_clean_failure(&out);
    assert_eq!(
        err.trim_end(),
        "beltctl: cannot open /dev/ttyNOSUCH9: No such file or directory"
    );
}

#[test]
fn a_failure_with_stdout_and_stderr_closed_is_no_panic() {
    // `beltctl ... 2>&1 | head` after the reader has gone: the message cannot be written, the
    // exit status still says it failed (101 would be a panic).
    let closed = || {
        let (reader, writer) = std::io::pipe().expect("pipe");
        drop(reader);
        std::process::Stdio::from(writer)
    };
    let (out, _) = beltctl_into(
        &["--port", "/dev/ttyNOSUCH9", "status"],
        LIMIT,
        closed(),
        closed(),
    );
    assert_eq!(out.status.code(), Some(1));
}

#[test]
fn a_file_is_not_a_serial_port() {
    let f = std::env::temp_dir().join(format!("beltctl-not-a-port-{}", std::process::id()));
    std::fs::write(&f, b"x").unwrap();
    let p = f.display().to_string();
    let (out, _) = beltctl(&["--port", &p, "enable"], LIMIT);
    let err = assert_clean_failure(&out);
    assert_eq!(
        err.trim_end(),
        format!("beltctl: cannot open {p}: not a serial port (a file)")
    );
    let _ = std::fs::remove_file(f);
}

#[test]
fn a_device_answering_garbage_is_not_a_drive() {
    let p = pty();
    let path = p.path.clone();
    let _fake = serve(
        p.master,
        FakeDrive::new(Faults {
            garbage: true,
            ..Faults::default()
        }),
    );
    let (out, _) = beltctl(&args(&path, &["status"]), LIMIT);
    let err = assert_clean_failure(&out);
    assert!(
        err.starts_with(&format!(
            "beltctl: {path} answers, but not with belt-drive frames: "
        )) && err.contains(" bytes of garbage and no valid frame in reply to status"),
        "{err}"
    );
}

#[test]
fn silence_times_out_after_the_configured_tries() {
    let p = pty();
    let path = p.path.clone();
    let fake = serve(
        p.master,
        FakeDrive::new(Faults {
            silent: true,
            ..Faults::default()
        }),
    );
    let (out, took) = beltctl(
        &[
            "--port",
            &path,
            "--timeout-ms",
            "80",
            "--retries",
            "4",
            "status",
        ],
        LIMIT,
    );
    let err = assert_clean_failure(&out);
    assert_eq!(
        err.trim_end(),
        format!(
            "beltctl: {path}: no reply to status within 80 ms after 4 tries (nothing received \
             at all: is the drive powered and connected?)"
        )
    );
    // 4 x 80 ms and the process around it.
    assert!(took >= Duration::from_millis(320), "{took:?}");
    assert!(took < Duration::from_secs(5), "{took:?}");
    assert_eq!(
        fake.drive.lock().unwrap().requests,
        vec![Request::Status; 4]
    );
}

#[test]
fn a_request_damaged_on_the_way_is_sent_again() {
    let p = pty();
    let path = p.path.clone();
    let fake = serve(
        p.master,
        FakeDrive::new(Faults {
            first_crc_error: true,
            ..Faults::default()
        }),
    );
    let (out, _) = beltctl(&args(&path, &["--json", "status"]), LIMIT);
    let err = text(&out.stderr);
    assert!(out.status.success(), "{err}");
    let j: serde_json::Value = serde_json::from_str(text(&out.stdout).trim()).unwrap();
    assert_eq!(j["model"], "model3");
    assert_eq!(j["record_crc"], "1234abcd");
    assert_eq!(
        j["flags"],
        serde_json::json!([
            "enabled",
            "calibrated",
            "homed",
            "amplifier_enabled",
            "configured"
        ])
    );
    assert!(j["motor_mm"].is_number(), "{j}");
    let reqs = fake.drive.lock().unwrap().requests.clone();
    assert_eq!(
        &reqs[..2],
        &[Request::Status, Request::Status],
        "sent twice"
    );
}

#[test]
fn lost_record_frames_are_reported() {
    let p = pty();
    let path = p.path.clone();
    let _fake = serve(
        p.master,
        FakeDrive::new(Faults {
            drop_records_seq: Some(3),
            ..Faults::default()
        }),
    );
    let csv = std::env::temp_dir().join(format!("beltctl-rec-{}.csv", std::process::id()));
    let csv_s = csv.display().to_string();
    let (out, _) = beltctl(
        &args(
            &path,
            &[
                "record",
                "--seconds",
                "0.3",
                "--every",
                "2",
                "--out",
                &csv_s,
            ],
        ),
        LIMIT,
    );
    let err = assert_clean_failure(&out);
    assert!(
        err.starts_with("beltctl: lost 1 of ") && err.contains("record frames (1 at seq 3)"),
        "{err}"
    );
    assert!(
        err.contains(&format!("{csv_s} holds what arrived")),
        "{err}"
    );
    let rows = std::fs::read_to_string(&csv).unwrap();
    let mut lines = rows.lines();
    assert_eq!(
        lines.next(),
        Some("tick,motor_counts,scale_counts,setpoint_counts,current_ma")
    );
    let ticks: Vec<u32> = lines
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert!(ticks.len() > 20, "{}", ticks.len());
    // Every 2 ticks, with the 4 samples of frame 3 missing.
    let jumps: Vec<u32> = ticks.windows(2).map(|w| w[1] - w[0]).collect();
    assert_eq!(jumps.iter().filter(|&&j| j != 2).count(), 1, "{jumps:?}");
    assert!(jumps.contains(&10));
    let _ = std::fs::remove_file(csv);
}

#[test]
fn a_whole_recording_succeeds() {
    let p = pty();
    let path = p.path.clone();
    let fake = serve(p.master, FakeDrive::new(Faults::default()));
    let csv = std::env::temp_dir().join(format!("beltctl-rec-ok-{}.csv", std::process::id()));
    let csv_s = csv.display().to_string();
    let (out, _) = beltctl(
        &args(
            &path,
            &["--json", "record", "--seconds", "0.2", "--out", &csv_s],
        ),
        LIMIT,
    );
    assert!(out.status.success(), "{}", text(&out.stderr));
    let j: serde_json::Value = serde_json::from_str(text(&out.stdout).trim()).unwrap();
    assert_eq!(j["lost_frames"], 0);
    let n = std::fs::read_to_string(&csv).unwrap().lines().count() - 1;
    assert_eq!(j["samples"], n as u64);
    let reqs = fake.drive.lock().unwrap().requests.clone();
    assert_eq!(reqs.first(), Some(&Request::Record { every_n_ticks: 1 }));
    assert_eq!(
        reqs.last(),
        Some(&Request::Record { every_n_ticks: 0 }),
        "stream stopped"
    );
    let _ = std::fs::remove_file(csv);
}

#[test]
fn moves_report_the_arrival_against_the_scale() {
    let p = pty();
    let path = p.path.clone();
    let _fake = serve(p.master, FakeDrive::new(Faults::default()));
    let (out, _) = beltctl(
        &args(
            &path,
            &[
                "--json",
                "move",
                "10",
                "20.5",
                "--settle-ms",
                "10",
                "--velocity",
                "100",
            ],
        ),
        LIMIT,
    );
    assert!(out.status.success(), "{}", text(&out.stderr));
    let lines: Vec<serde_json::Value> = text(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    assert_eq!(lines[1]["target_mm"], 20.5);
    // The fake arrives 7 scale counts (3.5 um) past every target.
    let e = lines[1]["scale_minus_target_um"].as_f64().unwrap();
    assert!((e - 3.5).abs() < 1e-6, "{e}");
    assert_eq!(lines[2]["count"], 2);
    assert!((lines[2]["max_um"].as_f64().unwrap() - 3.5).abs() < 1e-6);
}

#[test]
fn a_bad_config_file_is_refused_by_name_before_any_port_is_opened() {
    let f = std::env::temp_dir().join(format!("beltctl-cfg-{}.toml", std::process::id()));
    std::fs::write(&f, "\"rig.gear_ratio\" = 19.2\nrig.gear_ration = 3\n").unwrap();
    let p = f.display().to_string();
    let (out, _) = beltctl(&["--port", "/dev/ttyNOSUCH9", "config", "load", &p], LIMIT);
    let err = assert_clean_failure(&out);
    assert!(
        err.starts_with(&format!(
            "beltctl: {p}: rig.gear_ration: no such configuration field; did you mean"
        )),
        "{err}"
    );
    let _ = std::fs::remove_file(f);
}

/// A validation scenario in a scratch file: moves from 100 mm, the second to `second_mm`.
fn validation_file(tag: &str, second_mm: f64, velocity_mm_s: f64) -> std::path::PathBuf {
    let f = std::env::temp_dir().join(format!("beltctl-val-{tag}-{}.toml", std::process::id()));
    let text = format!(
        "name = \"mine\"\nstart_mm = 100.0\n\
         [[move]]\nto_mm = 150.0\nvelocity_mm_s = 80.0\naccel_mm_s2 = 1000.0\n\
         [[move]]\nto_mm = {second_mm:?}\nvelocity_mm_s = {velocity_mm_s:?}\naccel_mm_s2 = 500.0\n\
         retarget_after_ms = 20\n\
         [[move]]\nto_mm = 120.0\nvelocity_mm_s = 20.0\naccel_mm_s2 = 300.0\n"
    );
    std::fs::write(&f, text).unwrap();
    f
}

fn selections(reqs: &[Request]) -> Vec<belt_link::ModelKind> {
    reqs.iter()
        .filter_map(|r| match r {
            Request::Command(belt_link::Command::SelectModel(m)) => Some(*m),
            _ => None,
        })
        .collect()
}

#[test]
fn validation_places_with_each_compensator_and_selects_the_best_arrivals() {
    use belt_link::ModelKind;
    let f = validation_file("ok", 140.0, 50.0);
    let file = f.display().to_string();
    for select in [true, false] {
        let p = pty();
        let path = p.path.clone();
        let mut drive = FakeDrive::new(Faults::default());
        drive.arrival_offset_counts = 0;
        // 0.5 um a scale count: Model 2 arrives 4 um off, Model 3 3 um, the table -2.5 um.
        drive.model_offset_counts = [300, 10, 8, 6, 90, -5, 7];
        let fake = serve(p.master, drive);
        let mut rest = vec![
            "--json",
            "validate",
            "--scenario",
            &file,
            "--settle-ms",
            "5",
        ];
        rest.extend(["--models", "model2,model3,bidir_table,model4"]);
        if select {
            rest.push("--select");
        }
        let (out, _) = beltctl(&args(&path, &rest), LIMIT);
        assert!(out.status.success(), "{}", text(&out.stderr));
        let j: serde_json::Value = serde_json::from_str(text(&out.stdout).trim()).unwrap();
        // The retargeted second move has no arrival; the other two do.
        assert_eq!(j["arrivals"], 2);
        assert!((j["arrival_rms_um"]["model3"].as_f64().unwrap() - 3.0).abs() < 1e-9);
        assert!((j["arrival_max_um"]["bidir_table"].as_f64().unwrap() - 2.5).abs() < 1e-9);
        assert_eq!(j["arrival_rms_um"].as_object().unwrap().len(), 4);
        assert_eq!(j["best"], "bidir_table");
        let before = ModelKind::Table;
        assert_eq!(j["active"], if select { "bidir_table" } else { "model3" });
        let reqs = fake.drive.lock().unwrap().requests.clone();
        let last = if select {
            ModelKind::BidirTable
        } else {
            before
        };
        assert_eq!(
            selections(&reqs),
            [
                ModelKind::Exponential,
                ModelKind::Table,
                ModelKind::BidirTable,
                ModelKind::Operator,
                last
            ]
        );
        // Carriage moves (the compensator places them), three per pass.
        let carriage = reqs
            .iter()
            .filter(|r| matches!(r, Request::Command(belt_link::Command::MoveTo { .. })))
            .count();
        assert_eq!(carriage, 12);
    }
    let _ = std::fs::remove_file(f);
}

#[test]
fn a_validation_the_drive_cannot_run_is_refused_by_file_move_and_field_before_moving() {
    for (tag, second_mm, velocity, field) in [
        (
            "travel",
            320.0,
            50.0,
            "move 2: to_mm = 320 is outside the drive's travel",
        ),
        (
            "speed",
            140.0,
            400.0,
            "move 2: velocity_mm_s = 400 is above the drive's limit",
        ),
    ] {
        let f = validation_file(tag, second_mm, velocity);
        let file = f.display().to_string();
        let p = pty();
        let path = p.path.clone();
        let fake = serve(p.master, FakeDrive::new(Faults::default()));
        let (out, _) = beltctl(&args(&path, &["validate", "--scenario", &file]), LIMIT);
        let err = assert_clean_failure(&out);
        assert!(err.contains(&file) && err.contains(field), "{err}");
        let reqs = fake.drive.lock().unwrap().requests.clone();
        assert!(
            !reqs.iter().any(|r| matches!(r, Request::Command(_))),
            "{reqs:?}"
        );
        let _ = std::fs::remove_file(f);
    }
    // Names checked before any port is opened.
    let f = validation_file("names", 140.0, 50.0);
    let file = f.display().to_string();
    for (models, says) in [
        ("model3,model5", "\"model5\""),
        ("model3,model3", "model3 is named twice"),
    ] {
        let rest = ["--port", "/dev/ttyNOSUCH9", "validate", "--scenario", &file];
        let (out, _) = beltctl(&[&rest[..], &["--models", models]].concat(), LIMIT);
        let err = assert_clean_failure(&out);
        assert!(err.contains(says) && !err.contains("ttyNOSUCH9"), "{err}");
    }
    let _ = std::fs::remove_file(f);
}

#[test]
fn a_drive_configuration_that_does_not_build_is_refused_by_field_before_moving() {
    // Every value within its field's type, the whole refused: a crafted record, not beltctl's.
    let f = validation_file("whole", 140.0, 50.0);
    let file = f.display().to_string();
    type Edit = fn(&mut estimator_core::settings::Settings);
    let cases: [(Edit, &str); 2] = [
        (|s| s.max_velocity_mm_s = -1.0, "drive.max_velocity_mm_s"),
        (|s| s.rig.belt_pitch_mm = 0.0, "rig.belt_pitch_mm"),
    ];
    for (edit, field) in cases {
        let p = pty();
        let path = p.path.clone();
        let mut drive = FakeDrive::new(Faults::default());
        edit(&mut drive.settings);
        let fake = serve(p.master, drive);
        let (out, _) = beltctl(&args(&path, &["validate", "--scenario", &file]), LIMIT);
        let err = assert_clean_failure(&out);
        assert!(err.contains("refused") && err.contains(field), "{err}");
        let reqs = fake.drive.lock().unwrap().requests.clone();
        assert!(
            !reqs.iter().any(|r| matches!(r, Request::Command(_))),
            "{reqs:?}"
        );
    }
    let _ = std::fs::remove_file(f);
}

#[test]
fn a_validation_that_fails_stops_the_drive_and_restores_its_model() {
    use belt_link::ModelKind;
    let f = validation_file("fail", 140.0, 50.0);
    let file = f.display().to_string();
    // No calibration: refused before anything moves. A scale that does not follow: refused at
    // the first pass's seating stroke, the drive stopped and its model selected again.
    for (uncalibrated, says) in [
        (true, "validating model3 needs a calibration on the drive"),
        (
            false,
            "the linear scale moved 0.000 mm for 100.000 mm commanded",
        ),
    ] {
        let p = pty();
        let path = p.path.clone();
        let mut drive = FakeDrive::new(Faults::default());
        drive.calibrated = !uncalibrated;
        drive.scale_stuck_counts = (!uncalibrated).then_some(1234);
        let fake = serve(p.master, drive);
        let rest = ["validate", "--scenario", &file, "--models", "model3,model4"];
        let (out, _) = beltctl(&args(&path, &[&rest[..], &["--select"]].concat()), LIMIT);
        // Progress lines may come first; the error is one line, last.
        let err = text(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(!err.contains("panicked"), "{err}");
        let last = err.lines().last().unwrap_or_default();
        assert!(
            last.starts_with("beltctl: ") && last.contains(says),
            "{err}"
        );
        let reqs = fake.drive.lock().unwrap().requests.clone();
        let commands: Vec<&Request> = reqs
            .iter()
            .filter(|r| matches!(r, Request::Command(_)))
            .collect();
        if uncalibrated {
            assert!(commands.is_empty(), "{commands:?}");
        } else {
            assert_eq!(selections(&reqs), [ModelKind::Table, ModelKind::Table]);
            assert!(reqs.contains(&Request::Command(belt_link::Command::Stop)));
            assert!(!commands
                .iter()
                .any(|r| matches!(r, Request::Command(belt_link::Command::MoveTo { .. }))));
        }
    }
    let _ = std::fs::remove_file(f);
}

#[test]
fn long_rests_keep_the_drive_s_link_watchdog_fed() {
    // The drive faults after 0.5 s without a request (faults.link_timeout_s): a rest after a
    // move, or in a validation, polls it meanwhile.
    let f = validation_file("rest", 140.0, 50.0);
    let file = f.display().to_string();
    for rest in [
        vec!["move", "10", "--settle-ms", "1500"],
        vec![
            "validate",
            "--scenario",
            &file,
            "--models",
            "model3",
            "--settle-ms",
            "1500",
        ],
    ] {
        let p = pty();
        let path = p.path.clone();
        let fake = serve(p.master, FakeDrive::new(Faults::default()));
        let (out, _) = beltctl(&args(&path, &rest), LIMIT);
        assert!(out.status.success(), "{rest:?}: {}", text(&out.stderr));
        let times = fake.drive.lock().unwrap().arrivals.clone();
        let gap = times
            .windows(2)
            .map(|w| w[1] - w[0])
            .max()
            .unwrap_or_default();
        assert!(gap < Duration::from_millis(400), "{rest:?}: {gap:?}");
        assert!(times[times.len() - 1] - times[0] > Duration::from_millis(1500));
    }
    let _ = std::fs::remove_file(f);
}

/// A calibration directory for the paper rig whose region is what `validation_file`'s moves
/// cover (100-150 mm, 20-80 mm/s).
fn calibration_dir(tag: &str, scenario: &std::path::Path) -> std::path::PathBuf {
    use estimator_core::model::{ModelKind, ModelParams};
    let dir = std::env::temp_dir().join(format!("beltctl-cal-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let s = hil_sim::scenario::Scenario::load(&scenario.display().to_string()).unwrap();
    let cal = hil_sim::calibrate::Calibration {
        params: ModelParams::PAPER,
        fit_rms_um: [
            (ModelKind::Linear, 20.0),
            (ModelKind::Exponential, 19.0),
            (ModelKind::Table, 18.0),
            (ModelKind::Operator, 10.0),
        ],
        samples: 1,
        coverage: Some(hil_sim::coverage::Coverage::of([&s])),
    };
    hil_sim::calfile::save(&dir, &cal, &estimator_core::rig::Rig::PAPER).unwrap();
    dir
}

#[test]
fn moves_outside_the_calibrated_region_are_warned_about() {
    let f = validation_file("region", 140.0, 50.0);
    let file = f.display().to_string();
    let dir = calibration_dir("region", &f);
    let d = dir.display().to_string();
    // A calibration whose moves stayed at 200-250 mm: the validation's 100-150 mm leave it.
    let far = std::env::temp_dir().join(format!("beltctl-far-{}.toml", std::process::id()));
    std::fs::write(
        &far,
        "name = \"far\"\nstart_mm = 200.0\n[[move]]\nto_mm = 250.0\nvelocity_mm_s = 50.0\n\
         accel_mm_s2 = 500.0\n",
    )
    .unwrap();
    let far_dir = calibration_dir("far", &far);
    let d_far = far_dir.display().to_string();
    let validate = |dir| {
        let rest = [
            "validate",
            "--scenario",
            &file,
            "--models",
            "model3",
            "--settle-ms",
            "5",
        ];
        [&rest[..], &["--calibration", dir]].concat()
    };
    // The fake stands at 0 mm unless told: the way from there leaves the region.
    for (rest, warned) in [
        (
            vec!["move", "10", "--settle-ms", "5", "--calibration", &d],
            true,
        ),
        (
            vec![
                "move",
                "120",
                "--settle-ms",
                "5",
                "--velocity",
                "20",
                "--accel",
                "300",
                "--calibration",
                &d,
            ],
            false,
        ),
        (validate(&d), false),
        (validate(&d_far), true),
    ] {
        let p = pty();
        let path = p.path.clone();
        let mut drive = FakeDrive::new(Faults::default());
        if !warned {
            (drive.motor_um, drive.target_um) = (110_000, 110_000);
        }
        let _fake = serve(p.master, drive);
        let (out, _) = beltctl(&args(&path, &rest), LIMIT);
        let err = text(&out.stderr);
        assert!(out.status.success(), "{rest:?}: {err}");
        assert_eq!(
            err.contains("beltctl: warning: "),
            warned,
            "{rest:?}: {err}"
        );
    }
    // A directory that holds no calibration: refused by name before anything moves.
    let p = pty();
    let path = p.path.clone();
    let fake = serve(p.master, FakeDrive::new(Faults::default()));
    let (out, _) = beltctl(
        &args(&path, &["move", "10", "--calibration", "/nonexistent-cal"]),
        LIMIT,
    );
    let err = assert_clean_failure(&out);
    assert!(err.contains("/nonexistent-cal/calibration.bin"), "{err}");
    let reqs = fake.drive.lock().unwrap().requests.clone();
    assert!(
        !reqs.iter().any(|r| matches!(r, Request::Command(_))),
        "{reqs:?}"
    );
    let _ = std::fs::remove_dir_all(dir);
    let _ = std::fs::remove_dir_all(far_dir);
    let _ = std::fs::remove_file(far);
    let _ = std::fs::remove_file(f);
}

/// Whether any of `requests` moved the drive or started a recording.
fn moved_or_recorded(requests: &[belt_link::Request]) -> bool {
    requests.iter().any(|r| {
        matches!(
            r,
            belt_link::Request::Command(belt_link::Command::MoveTo { .. })
                | belt_link::Request::Command(belt_link::Command::MoveMotorTo { .. })
                | belt_link::Request::Record { .. }
        )
    })
}

#[test]
fn a_calibration_whose_output_cannot_be_written_is_refused_before_any_move() {
    let file = std::env::temp_dir().join(format!("beltctl-out-{}.txt", std::process::id()));
    std::fs::write(&file, "not a directory").unwrap();
    for out_dir in [file.clone(), file.join("below")] {
        let p = pty();
        let path = p.path.clone();
        let fake = serve(p.master, FakeDrive::new(Faults::default()));
        let d = out_dir.display().to_string();
        let (out, _) = beltctl(&args(&path, &["calibrate", "--out", &d]), LIMIT);
        let err = assert_clean_failure(&out);
        assert!(
            err.contains(&format!("--out {d}: cannot be written")),
            "{err}"
        );
        let moved = moved_or_recorded(&fake.drive.lock().unwrap().requests);
        assert!(!moved, "{d}: the drive was moved or recorded");
    }
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "not a directory");
    let _ = std::fs::remove_file(file);
}

#[test]
fn a_refused_or_empty_recording_leaves_an_existing_file_as_it_was() {
    for (faults, expect) in [
        (
            Faults {
                refuse_record: true,
                ..Faults::default()
            },
            "refused",
        ),
        (
            Faults {
                mute_records: true,
                ..Faults::default()
            },
            "the drive sent no samples in 0.3 s",
        ),
    ] {
        let p = pty();
        let path = p.path.clone();
        let _fake = serve(p.master, FakeDrive::new(faults));
        let csv = std::env::temp_dir().join(format!("beltctl-keep-{}.csv", std::process::id()));
        std::fs::write(&csv, "precious\n").unwrap();
        let csv_s = csv.display().to_string();
        let (out, _) = beltctl(
            &args(&path, &["record", "--seconds", "0.3", "--out", &csv_s]),
            LIMIT,
        );
        let err = assert_clean_failure(&out);
        assert!(err.contains(expect), "{err}");
        assert_eq!(std::fs::read_to_string(&csv).unwrap(), "precious\n");
        let dir = csv.parent().unwrap();
        let left: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .filter_map(|e| e.ok())
            .filter(|e| {
                e.file_name()
                    .to_string_lossy()
                    .starts_with(".beltctl-keep-")
            })
            .collect();
        assert!(left.is_empty(), "partial file left behind");
        let _ = std::fs::remove_file(csv);
    }
}

/// A `--timeout-ms` above the default is held against the drive's link watchdog (0.5 s on the
/// fake): the drive hears nothing while the tool waits, so a lost reply would stop an enabled
/// drive. Refused by the option with the field and the longest wait it allows, before any
/// other request; a wait within it works.
#[test]
fn a_reply_wait_the_drive_s_link_watchdog_would_not_survive_is_refused() {
    let p = pty();
    let path = p.path.clone();
    let fake = serve(p.master, FakeDrive::new(Faults::default()));
    let (out, _) = beltctl(&["--port", &path, "--timeout-ms", "450", "status"], LIMIT);
    let err = assert_clean_failure(&out);
    for says in [
        "--timeout-ms 450",
        "faults.link_timeout_s",
        "0.5 s",
        "at most 400 ms",
    ] {
        assert!(err.contains(says), "lacks `{says}`: {err}");
    }
    let key = estimator_core::ConfigField::FaultsLinkTimeoutS as u8;
    assert_eq!(
        fake.drive.lock().unwrap().requests,
        vec![Request::ConfigGet { key }]
    );
    let (out, _) = beltctl(&["--port", &path, "--timeout-ms", "400", "status"], LIMIT);
    assert!(out.status.success(), "{}", text(&out.stderr));
}

/// `calibrate --machine` with a plant file of another geometry than the drive's (a 15-tooth
/// pulley and a 500-line encoder against the paper rig's) is refused naming the file and both
/// geometries, before any move; a machine file that cannot be read names it too.
#[test]
fn a_machine_of_another_geometry_is_refused_before_any_move() {
    let other = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../hil-sim/presets/variants/other-geometry.toml"
    );
    let missing = "/nonexistent-machine.toml";
    for (machine, says) in [(other, "is not the drive's"), (missing, missing)] {
        let p = pty();
        let path = p.path.clone();
        let fake = serve(p.master, FakeDrive::new(Faults::default()));
        let out_dir = std::env::temp_dir().join(format!("beltctl-machine-{}", std::process::id()));
        let d = out_dir.display().to_string();
        let (out, _) = beltctl(
            &args(&path, &["calibrate", "--out", &d, "--machine", machine]),
            LIMIT,
        );
        let err = assert_clean_failure(&out);
        assert!(err.contains("--machine") && err.contains(says), "{err}");
        let moved = moved_or_recorded(&fake.drive.lock().unwrap().requests);
        assert!(!moved, "{machine}: the drive was moved or recorded");
        let _ = std::fs::remove_dir_all(out_dir);
    }
}
