//! `cargo bench -p hil-sim --bench sim_speed`: simulation speed (simulated seconds per wall-clock
//! second) of the closed loop on the Fig. 18 and reversals scenarios: plant + drive in-process
//! (one core), then Fig. 18 with the firmware in the loop under QEMU over both links (the PIL
//! pipe and USART2), if the QEMU firmware is built (`cargo fw-qemu`; `BELT_DRIVE_ELF` to choose).

use std::time::Instant;

use estimator_core::model::{ModelKind, ModelParams};
use hil_sim::eval::{run_in_process, run_pil};
use hil_sim::pil::qemu::LogSink;
use hil_sim::pil::{PilOptions, Transport};
use hil_sim::plant::PlantParams;
use hil_sim::run::RunConfig;
use hil_sim::scenario::Scenario;

fn report(name: &str, how: &str, sim: f64, wall: f64, ticks: usize) {
    println!(
        "{name:<10} {how:<14} {sim:7.1} s simulated in {wall:7.3} s wall: {:8.2}x real time ({ticks} ticks)",
        sim / wall
    );
}

fn main() {
    let plant = PlantParams::paper_rig();
    for name in ["fig18", "reversals"] {
        let s = Scenario::load(name).expect("preset");
        let start = Instant::now();
        let t = run_in_process(
            &s,
            &plant,
            &ModelParams::PAPER,
            ModelKind::Table,
            1,
            &mut |_| {},
        )
        .expect("run");
        let wall = start.elapsed().as_secs_f64();
        let sim = t.records.last().map_or(0.0, |r| r.t_s);
        report(name, "in-process", sim, wall, t.records.len());
    }

    let elf = std::env::var_os("BELT_DRIVE_ELF")
        .map(Into::into)
        .unwrap_or_else(|| PilOptions::default_elf(None));
    if !elf.exists() {
        println!("PIL: {} not built (cargo fw-qemu): skipped", elf.display());
        return;
    }
    let s = Scenario::load("fig18").expect("preset");
    for (how, transport) in [
        ("PIL pipe", Transport::Pipe),
        ("PIL USART2", Transport::Usart),
    ] {
        let mut opts = PilOptions::new(&elf);
        opts.log = LogSink::Discard;
        opts.transport = transport;
        let start = Instant::now();
        let t = run_pil(
            &s,
            &plant,
            &ModelParams::PAPER,
            ModelKind::Table,
            &RunConfig::default(),
            &opts,
            &mut |_| {},
        )
        .expect("PIL run");
        let wall = start.elapsed().as_secs_f64();
        let sim = t.records.last().map_or(0.0, |r| r.t_s);
        report("fig18", how, sim, wall, t.records.len());
    }
}
