//! The drive's status for people (a table) and programs (one JSON object), every bit by name.

use belt_link::{reset_cause, status_flags, Faults, LinkError, WireStatus};
use estimator_core::drive::SCALE_COUNTS_PER_UM;
use estimator_core::rig::Rig;
use serde_json::{json, Value};

use crate::error::link_error_name;

/// Every status flag with its name, in bit order.
pub const FLAG_NAMES: [(u8, &str); 8] = [
    (status_flags::MOVING, "moving"),
    (status_flags::ENABLED, "enabled"),
    (status_flags::CALIBRATED, "calibrated"),
    (status_flags::STREAMING, "streaming"),
    (status_flags::HOMED, "homed"),
    (status_flags::AMPLIFIER_ENABLED, "amplifier_enabled"),
    (status_flags::CONFIGURED, "configured"),
    (status_flags::HOMING, "homing"),
];

/// Names of the set flags.
pub fn flag_names(flags: u8) -> Vec<&'static str> {
    FLAG_NAMES
        .iter()
        .filter(|(b, _)| flags & b != 0)
        .map(|(_, n)| *n)
        .collect()
}

/// Names of the set fault bits; unknown bits as `bit N`.
pub fn fault_names(faults: Faults) -> Vec<String> {
    (0..16)
        .map(|i| 1u16 << i)
        .filter(|&b| faults.has(b))
        .map(|b| match Faults::NAMES.iter().find(|(f, _)| *f == b) {
            Some((_, n)) => n.to_string(),
            None => format!("bit {}", b.trailing_zeros()),
        })
        .collect()
}

/// Names of the set reset-cause bits.
pub fn reset_names(cause: u8) -> Vec<&'static str> {
    reset_cause::NAMES
        .iter()
        .filter(|(b, _)| cause & b != 0)
        .map(|(_, n)| *n)
        .collect()
}

/// The linear scale's reading, micrometres.
pub fn scale_um(s: &WireStatus) -> f64 {
    s.scale_counts.0 as f64 / SCALE_COUNTS_PER_UM as f64
}

/// The motor's position in millimetres of nominal travel, where the geometry is known.
pub fn motor_mm(s: &WireStatus, rig: Option<&Rig>) -> Option<f64> {
    rig.map(|r| s.motor_counts.to_mm(r.counts_per_mm()))
}

fn last_error(code: u8) -> Value {
    match code {
        0 => Value::Null,
        c => match LinkError::from_code(c) {
            Some(e) => json!(link_error_name(e)),
            None => json!(format!("code {c}")),
        },
    }
}

/// One JSON object: flags (as a list of names, and each as a boolean), faults and reset causes
/// by name, positions in mm and um.
pub fn to_json(s: &WireStatus, rig: Option<&Rig>) -> Value {
    let mut v = json!({
        "tick": s.tick,
        "flags": flag_names(s.flags),
        "faults": fault_names(s.faults),
        "model": s.model.as_str(),
        "motor_counts": s.motor_counts.0,
        "motor_mm": motor_mm(s, rig),
        "scale_counts": s.scale_counts.0,
        "scale_um": scale_um(s),
        "carriage_estimate_um": s.carriage_estimate_um,
        "carriage_target_um": s.carriage_target_um,
        "record_crc": format!("{:08x}", s.record_crc),
        "reset_cause": reset_names(s.reset_cause),
        "missed_ticks": s.missed_ticks,
        "scale_glitches": s.scale_glitches,
        "frames_ok": s.frames_ok,
        "frames_bad": s.frames_bad,
        "last_link_error": last_error(s.last_error),
        "stack_peak_bytes": s.stack_peak_bytes,
    });
    // Each flag also on its own, for scripts (`"configured": true`).
    if let Value::Object(m) = &mut v {
        for (bit, name) in FLAG_NAMES {
            m.insert(name.to_string(), json!(s.flags & bit != 0));
        }
    }
    v
}

fn or_none(v: Vec<String>) -> String {
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

/// A table for people.
pub fn to_table(port: &str, s: &WireStatus, rig: Option<&Rig>) -> String {
    let motor = match motor_mm(s, rig) {
        Some(mm) => format!("{mm:.4} mm ({} counts)", s.motor_counts),
        None => format!("{} counts (geometry unknown)", s.motor_counts),
    };
    let strings = |v: Vec<&str>| v.into_iter().map(String::from).collect::<Vec<_>>();
    let rows = [
        ("port", port.to_string()),
        ("flags", or_none(strings(flag_names(s.flags)))),
        ("faults", or_none(fault_names(s.faults))),
        ("model", s.model.as_str().to_string()),
        ("motor", motor),
        (
            "scale",
            format!("{:.1} um ({} counts)", scale_um(s), s.scale_counts),
        ),
        (
            "carriage estimate",
            format!("{:.3} mm", s.carriage_estimate_um as f64 / 1000.0),
        ),
        (
            "carriage target",
            format!("{:.3} mm", s.carriage_target_um as f64 / 1000.0),
        ),
        (
            "stored record",
            match s.record_crc {
                0 => "none (00000000)".to_string(),
                c => format!("crc {c:08x}"),
            },
        ),
        ("reset cause", or_none(strings(reset_names(s.reset_cause)))),
        ("tick", s.tick.to_string()),
        (
            "link",
            format!(
                "{} frames ok, {} bad, last error {}",
                s.frames_ok,
                s.frames_bad,
                match last_error(s.last_error) {
                    Value::String(e) => e,
                    _ => "none".into(),
                }
            ),
        ),
        ("missed ticks", s.missed_ticks.to_string()),
        ("scale glitches", s.scale_glitches.to_string()),
        (
            "stack peak",
            match s.stack_peak_bytes {
                0 => "not measured".into(),
                b => format!("{b} bytes"),
            },
        ),
    ];
    rows.iter().map(|(k, v)| format!("{k:<18} {v}\n")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use belt_link::{MotorCounts, ScaleCounts};

    #[test]
    fn bits_are_named() {
        let s = WireStatus {
            flags: status_flags::ENABLED | status_flags::HOMED | status_flags::HOMING,
            faults: Faults(Faults::STALL | Faults::FOLLOWING_ERROR | 1 << 15),
            reset_cause: reset_cause::POWER_ON,
            motor_counts: MotorCounts(18679),
            scale_counts: ScaleCounts(20001),
            record_crc: 0xab,
            model: belt_link::ModelKind::Table,
            ..WireStatus::default()
        };
        let j = to_json(&s, Some(&Rig::PAPER));
        assert_eq!(j["flags"], json!(["enabled", "homed", "homing"]));
        assert_eq!(
            (j["homed"].clone(), j["moving"].clone()),
            (json!(true), json!(false))
        );
        assert_eq!(j["faults"], json!(["following_error", "stall", "bit 15"]));
        assert_eq!(j["reset_cause"], json!(["power_on"]));
        assert_eq!(j["model"], "model3");
        assert_eq!(j["record_crc"], "000000ab");
        assert_eq!(j["scale_um"], 10000.5);
        assert!((j["motor_mm"].as_f64().unwrap() - 10.0).abs() < 0.001);
        assert_eq!(to_json(&s, None)["motor_mm"], Value::Null);
        let t = to_table("/dev/x", &s, None);
        assert!(t.contains("following_error, stall, bit 15"), "{t}");
    }
}
