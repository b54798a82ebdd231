//! Processor in the loop: the firmware under QEMU and the core in-process run the Fig. 18
//! scenario through the same plant, with the same calibration and seed, and must agree bit for bit
//! on every tick (current and telemetry, the estimate included).
//!
//! Needs the QEMU firmware (`cargo fw-qemu`), so it is ignored by a plain `cargo test`;
//! `.ci/test` builds the firmware and runs it with `--ignored`.

use estimator_core::model::ModelKind;
use hil_sim::eval;
use hil_sim::pil::qemu::LogSink;
use hil_sim::pil::PilOptions;
use hil_sim::plant::PlantParams;
use hil_sim::scenario::Scenario;

mod common;
use common::paper_calibration;

/// The firmware under test: `BELT_DRIVE_ELF`, or the `cargo fw-qemu` output.
fn elf() -> std::path::PathBuf {
    let elf = std::env::var_os("BELT_DRIVE_ELF")
        .map(Into::into)
        .unwrap_or_else(|| PilOptions::default_elf(None));
    assert!(
        elf.exists(),
        "{}: build the firmware with `cargo fw-qemu` first",
        elf.display()
    );
    elf
}

#[test]
#[ignore = "needs the QEMU firmware ELF (cargo fw-qemu); run by .ci/test"]
fn fig18_pil_is_bit_identical_to_the_host() {
    let elf = elf();
    let plant = PlantParams::paper_rig();
    let cal = paper_calibration();
    let scenario = Scenario::load("fig18").unwrap();
    // Model 3, and Model 4 with the belt observer the default calibration gives it.
    assert!(
        cal.params.model4.belt.is_some(),
        "the paper rig's Model 4 has its belt observer"
    );
    for model in [ModelKind::Table, ModelKind::Operator] {
        let pil = assert_pil_matches_host(elf.clone(), &plant, &cal.params, &scenario, model, 3);
        eprintln!(
            "fig18, {model}: {} ticks bit-identical between host and firmware under QEMU",
            pil.records.len()
        );
    }
}

/// Runs `scenario` in-process and with the firmware under QEMU (the pipe transport) with the
/// same plant, calibration, model and seed, asserts every tick identical, and returns the
/// firmware's trace.
fn assert_pil_matches_host(
    elf: std::path::PathBuf,
    plant: &PlantParams,
    params: &estimator_core::model::ModelParams,
    scenario: &Scenario,
    model: ModelKind,
    seed: u64,
) -> hil_sim::run::Trace {
    let host = eval::run_in_process(scenario, plant, params, model, seed, &mut |_| {}).unwrap();
    let mut opts = PilOptions::new(elf);
    opts.log = LogSink::Discard;
    let rc = hil_sim::run::RunConfig {
        seed,
        ..Default::default()
    };
    let pil = eval::run_pil(scenario, plant, params, model, &rc, &opts, &mut |_| {}).unwrap();
    assert_eq!(host.records.len(), pil.records.len(), "tick counts differ");
    for (k, (h, p)) in host.records.iter().zip(&pil.records).enumerate() {
        assert_eq!(h, p, "tick {k} differs: host {h:?} firmware {p:?}");
    }
    pil
}

/// Carriage placement with the firmware in the loop: the same carriage-space moves give the same
/// arrival errors, to the bit, as the core in-process. This one runs over the emulated USART2,
/// byte by byte as on the board's serial line (the others use the faster PIL pipe).
#[test]
#[ignore = "needs the QEMU firmware ELF (cargo fw-qemu); run by .ci/test"]
fn placement_pil_matches_the_host() {
    let elf = elf();
    let plant = PlantParams::paper_rig();
    let cal = paper_calibration();
    let moves = [
        (150.0, 80.0, 2000.0),
        (100.0, 60.0, 1500.0),
        (102.0, 20.0, 500.0),
        (60.0, 100.0, 3000.0),
    ];
    let host = hil_sim::placement::arrival_errors_in_process(
        &plant,
        &cal.params,
        ModelKind::Table,
        30.0,
        &moves,
        5,
    )
    .unwrap();
    let mut opts = PilOptions::new(elf);
    opts.log = LogSink::Discard;
    opts.transport = hil_sim::pil::Transport::Usart;
    let mut fw = hil_sim::pil::PilController::start(&opts).unwrap();
    let rig = estimator_core::rig::Rig::PAPER;
    let image = estimator_core::image::of_params(&cal.params, &rig).unwrap();
    fw.load_calibration(&image).unwrap();
    let pil = hil_sim::placement::arrival_errors(
        &mut fw,
        &plant,
        &rig,
        ModelKind::Table,
        30.0,
        &moves,
        5,
    )
    .unwrap();
    assert_eq!(fw.shutdown(0).unwrap(), 0);
    assert_eq!(
        host, pil,
        "arrival errors (um): host {host:?}, firmware {pil:?}"
    );
    eprintln!("placement: firmware under QEMU = host, arrival errors {pil:?} um");
}

/// Every compensator places the carriage identically with the firmware under QEMU: the
/// `"positioning"` JSON of a short scenario (a reversal, a retarget with new limits in mid-move
/// that reverses, moves at several limits) is the same text from both.
#[test]
#[ignore = "needs the QEMU firmware ELF (cargo fw-qemu); run by .ci/test"]
fn positioning_json_pil_matches_the_host() {
    let elf = elf();
    let plant = PlantParams::paper_rig();
    let cal = paper_calibration();
    let scenario = Scenario::from_toml_str(
        r#"
name = "placement-pil"
start_mm = 40.0
[[move]]
to_mm = 90.0
velocity_mm_s = 120.0
accel_mm_s2 = 3000.0
dwell_ms = 100
[[move]]
to_mm = 70.0
velocity_mm_s = 40.0
accel_mm_s2 = 800.0
retarget_after_ms = 150
[[move]]
to_mm = 95.0
velocity_mm_s = 150.0
accel_mm_s2 = 4000.0
dwell_ms = 100
[[move]]
to_mm = 60.0
velocity_mm_s = 60.0
accel_mm_s2 = 1500.0
"#,
    )
    .unwrap();
    let rc = hil_sim::run::RunConfig {
        seed: 9,
        carriage_space: true,
        ..Default::default()
    };
    let json = |placed: Vec<hil_sim::placement::Placement>| {
        let rows: Vec<_> = placed
            .into_iter()
            .map(|p| (p.name, p.positioning))
            .collect();
        eval::to_json(&scenario.name, 0, &[], &rows).unwrap()
    };
    let host = hil_sim::placement::compare(&scenario, &cal.params, &plant.rig(), &mut |model| {
        hil_sim::placement::run_carriage_space(
            &scenario,
            &plant,
            &cal.params,
            model,
            rc.seed,
            &mut |_| {},
        )
    })
    .unwrap();
    assert!(
        host.iter().all(|p| p.positioning.moves_at_rest == 3),
        "{host:?}"
    );
    let host = json(host);
    let mut opts = PilOptions::new(elf);
    opts.log = LogSink::Discard;
    let pil = json(
        hil_sim::placement::compare(&scenario, &cal.params, &plant.rig(), &mut |model| {
            eval::run_pil(
                &scenario,
                &plant,
                &cal.params,
                model,
                &rc,
                &opts,
                &mut |_| {},
            )
        })
        .unwrap(),
    );
    assert_eq!(
        host, pil,
        "positioning differs:\nhost {host}\nfirmware {pil}"
    );
    eprintln!("positioning: firmware under QEMU = host: {pil}");
}

/// A drive train that is not the paper rig's (a 15-tooth pulley, a 500-line encoder: 3.5 times
/// fewer counts per millimetre): the firmware under QEMU is configured for it over the link (the
/// host-built configuration image), loads that plant's calibration, and runs a short scenario
/// bit for bit like the core in-process.
#[test]
#[ignore = "needs the QEMU firmware ELF (cargo fw-qemu); run by .ci/test"]
fn another_geometry_pil_is_bit_identical_to_the_host() {
    let elf = elf();
    let mut plant = PlantParams::paper_rig();
    plant.pulley.teeth = 15;
    plant.encoder.lines = 500;
    plant.validate().unwrap();
    assert_ne!(plant.rig(), PlantParams::paper_rig().rig());
    let cal = eval::calibrate_plant(&plant, &mut |_, _| {}).unwrap();
    let scenario = Scenario::from_toml_str(
        r#"
name = "geometry-pil"
start_mm = 40.0
[[move]]
to_mm = 110.0
velocity_mm_s = 150.0
accel_mm_s2 = 3000.0
dwell_ms = 100
[[move]]
to_mm = 70.0
velocity_mm_s = 50.0
accel_mm_s2 = 1000.0
dwell_ms = 100
[[move]]
to_mm = 90.0
velocity_mm_s = 100.0
accel_mm_s2 = 2000.0
"#,
    )
    .unwrap();
    let pil = assert_pil_matches_host(
        elf,
        &plant,
        &cal.params,
        &scenario,
        ModelKind::Exponential,
        5,
    );
    // The estimate is in use (the plant's calibration, not the paper rig's Table 2).
    assert!(
        pil.records
            .iter()
            .any(|r| r.out.telemetry.est_error_um != 0),
        "no estimate"
    );
}

#[test]
#[ignore = "needs the QEMU firmware ELF (cargo fw-qemu); run by .ci/test"]
fn qemu_run_stops_when_the_reader_of_its_log_goes() {
    // `qemu-run ELF | head -1`: the firmware idles silently after its boot lines, so only a check
    // that does not wait for the next write notices the reader has gone. Without it the run
    // lasts until the deadline and exits 124.
    use std::io::BufRead;
    let (reader, writer) = std::io::pipe().expect("pipe");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_qemu-run"))
        .args(["--timeout", "20"])
        .arg(elf())
        .stdin(std::process::Stdio::null())
        .stdout(writer)
        .spawn()
        .expect("spawn qemu-run");
    let mut first = String::new();
    std::io::BufReader::new(reader)
        .read_line(&mut first)
        .expect("the first log line");
    assert!(first.contains("belt-drive"), "{first}");
    // The reader is dropped here, as `head` exits.
    let status = child.wait().expect("qemu-run ends");
    assert_eq!(status.code(), Some(141));
}
