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
        serde_json::json!(["enabled", "homed", "amplifier_enabled", "configured"])
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
