//! The drive's configuration over the link, by the field names of the drive's own table
//! (`estimator_core::settings::FIELDS`): read, stage and apply, files to load and dump.

use std::path::Path;

use belt_link::{status_flags, Reply, Request};
use estimator_core::endpoint::config_parts_requests;
use estimator_core::rig::Rig;
use estimator_core::settings::{self, Field, Settings, FIELDS};

use crate::error::ToolError;
use crate::link::Link;

/// One field as the drive holds it.
#[derive(Clone, Copy)]
pub struct FieldValue {
    /// The field.
    pub field: &'static Field,
    /// The value the drive runs with.
    pub active: f64,
    /// The value staged for the next apply (equal to `active` when nothing is staged).
    pub staged: f64,
}

impl FieldValue {
    /// The staged value when it differs from the active one (bit for bit).
    pub fn staged_change(&self) -> Option<f64> {
        (self.staged.to_bits() != self.active.to_bits()).then_some(self.staged)
    }
}

/// Why a configuration argument (`NAME=VALUE`, a name, a value) was refused; names the field.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ArgError {
    /// No field has this name.
    #[error("{name}: no such configuration field (`beltctl config get` lists them)")]
    Unknown {
        /// The name given.
        name: String,
    },
    /// No field has this name; these look like it.
    #[error("{name}: no such configuration field; did you mean {}?", near.join(", "))]
    UnknownNear {
        /// The name given.
        name: String,
        /// Up to 12 field names in the same section or with the same last part.
        near: Vec<&'static str>,
    },
    /// The value is not a number (nor `true`/`false` for a 0-or-1 field).
    #[error("{field}: {text:?} is not a number")]
    NotANumber {
        /// The field.
        field: &'static str,
        /// What was written.
        text: String,
    },
    /// The field cannot hold the value (the drive's own field check).
    #[error("{source} (unit {unit}{})", if *whole { ", a whole number" } else { "" })]
    Refused {
        /// The drive's reason, naming the field.
        source: settings::SettingsError,
        /// The field's unit.
        unit: &'static str,
        /// The field holds whole numbers only.
        whole: bool,
    },
    /// Not of the form `NAME=VALUE`.
    #[error("{0}: write NAME=VALUE, e.g. rig.gear_ratio=19.2")]
    NotAnAssignment(String),
}

/// The field named `name`; an unknown name is refused with the names it resembles.
pub fn lookup(name: &str) -> Result<&'static Field, ArgError> {
    if let Some(f) = settings::field_named(name) {
        return Ok(f);
    }
    // Same section, or the same last part in another section.
    let (section, last) = name.rsplit_once('.').unwrap_or(("", name));
    let near: Vec<&str> = FIELDS
        .iter()
        .filter(|f| {
            let (s, l) = f.name().rsplit_once('.').unwrap_or(("", f.name()));
            (!section.is_empty() && s == section) || l == last || l.contains(last)
        })
        .map(|f| f.name())
        .take(12)
        .collect();
    let name = name.to_string();
    Err(if near.is_empty() {
        ArgError::Unknown { name }
    } else {
        ArgError::UnknownNear { name, near }
    })
}

/// Checks `value` for `field` with the drive's own field check (`Settings::set`): finite, in
/// the field type's range, whole where it must be. Whether the configuration as a whole makes
/// sense is the drive's check at apply.
pub fn check(field: &Field, value: f64) -> Result<(), ArgError> {
    let mut scratch = Settings::PAPER;
    scratch
        .set(field.key(), value)
        .map_err(|source| ArgError::Refused {
            source,
            unit: field.unit,
            whole: field.whole,
        })
}

/// Parses a value written on the command line: a number, or `true`/`false` for the 0-or-1 fields.
pub fn parse_value(field: &Field, text: &str) -> Result<f64, ArgError> {
    let t = text.trim();
    let v = match t {
        "true" if field.whole => 1.0,
        "false" if field.whole => 0.0,
        _ => t.parse::<f64>().map_err(|_| ArgError::NotANumber {
            field: field.name(),
            text: t.to_string(),
        })?,
    };
    check(field, v)?;
    Ok(v)
}

/// Parses `NAME=VALUE`.
pub fn parse_assignment(arg: &str) -> Result<(&'static Field, f64), ArgError> {
    let (name, value) = arg
        .split_once('=')
        .ok_or_else(|| ArgError::NotAnAssignment(arg.to_string()))?;
    let field = lookup(name.trim())?;
    Ok((field, parse_value(field, value)?))
}

/// Reads one field.
pub fn get(link: &mut Link, field: &'static Field) -> Result<FieldValue, ToolError> {
    let req = Request::ConfigGet { key: field.key() };
    match link.call(&req)? {
        Reply::ConfigValue {
            active_bits,
            staged_bits,
            ..
        } => Ok(FieldValue {
            field,
            active: f64::from_bits(active_bits),
            staged: f64::from_bits(staged_bits),
        }),
        other => Err(link.unexpected(&req, &other)),
    }
}

/// Reads every field, in key order.
pub fn get_all(link: &mut Link) -> Result<Vec<FieldValue>, ToolError> {
    FIELDS.iter().map(|f| get(link, f)).collect()
}

/// The drive's active configuration as [`Settings`], for a command that moves or plans by it:
/// a value the drive holds that its own table would refuse, or a configuration that would not
/// build as a whole (a drive that `beltctl` configured cannot hold one, a crafted record can),
/// is reported by name.
pub fn settings(link: &mut Link) -> Result<Settings, ToolError> {
    let s = read_settings(link, false)?;
    s.parts_image().map_err(|e| {
        ToolError::Drive(format!(
            "{}: the drive's configuration is refused as a whole: {}",
            link.name(),
            with_unit(&e)
        ))
    })?;
    Ok(s)
}

/// A configuration refusal with the field's unit.
fn with_unit(e: &estimator_core::ConfigError) -> String {
    match settings::field(settings::key_of(e)) {
        Some(f) => format!("{e} (unit {})", f.unit),
        None => e.to_string(),
    }
}

/// The active (or, with `staged`, the staged) values as [`Settings`], each checked by its field:
/// the drive stores them unread, so a refused one is named here.
fn read_settings(link: &mut Link, staged: bool) -> Result<Settings, ToolError> {
    let mut s = Settings::PAPER;
    for v in get_all(link)? {
        let value = if staged { v.staged } else { v.active };
        s.set(v.field.key(), value).map_err(|e| {
            ToolError::Drive(format!(
                "{}: the drive's {}configuration holds {} = {value}: {e}",
                link.name(),
                if staged { "staged " } else { "" },
                v.field.name(),
            ))
        })?;
    }
    Ok(s)
}

/// The drive's drive-train geometry (the `rig.*` fields).
pub fn rig(link: &mut Link) -> Result<Rig, ToolError> {
    let mut s = Settings::PAPER;
    for f in FIELDS.iter().filter(|f| f.name().starts_with("rig.")) {
        let v = get(link, f)?;
        s.set(f.key(), v.active).map_err(|e| {
            ToolError::Drive(format!("{}: the drive's {}: {e}", link.name(), f.name()))
        })?;
    }
    // Each field in its type, the geometry as a whole checked too (a zero pitch would make
    // every count infinite millimetres).
    s.rig.validate().map_err(|e| {
        ToolError::Drive(format!(
            "{}: the drive's geometry is refused: {}",
            link.name(),
            with_unit(&e)
        ))
    })?;
    Ok(s.rig)
}

/// Fails unless the drive is disabled: applying a configuration and saving need it.
pub fn require_disabled(link: &mut Link, what: &str) -> Result<(), ToolError> {
    let s = link.status()?;
    if s.flags & status_flags::ENABLED != 0 {
        return Err(ToolError::Drive(format!(
            "{what} needs the drive disabled; it is enabled: run `beltctl disable` first"
        )));
    }
    Ok(())
}

/// Stages every value and applies them together; `source` (a file or "command line") names
/// where they came from in a refusal.
pub fn set_and_apply(
    link: &mut Link,
    values: &[(&'static Field, f64)],
    source: &str,
) -> Result<(), ToolError> {
    require_disabled(link, "changing the configuration")?;
    // What these fields held staged before: a refusal puts it back, so that bad input changes
    // nothing on the drive (not even its staged values).
    let before = values
        .iter()
        .map(|(f, _)| get(link, f).map(|v| (*f, v.staged)))
        .collect::<Result<Vec<_>, _>>()?;
    let result = stage_and_apply(link, values, source);
    let Err(e) = result else {
        return Ok(());
    };
    // Only a refusal is known to have changed nothing: after a lost reply the drive may have
    // applied the values, and staging the old ones would undo them at the next apply.
    if !matches!(e, ToolError::Drive(_)) {
        return Err(e);
    }
    let restored = before.iter().all(|(f, v)| {
        link.acked(&Request::ConfigSet {
            key: f.key(),
            value_bits: v.to_bits(),
        })
        .is_ok()
    });
    Err(match e {
        ToolError::Drive(why) if restored => ToolError::Drive(format!(
            "{why}; nothing changed (the staged values put back)"
        )),
        ToolError::Drive(why) => ToolError::Drive(format!(
            "{why}; the values may stay staged (`beltctl config get` shows them) until an \
             apply succeeds"
        )),
        other => other,
    })
}

fn stage_and_apply(
    link: &mut Link,
    values: &[(&'static Field, f64)],
    source: &str,
) -> Result<(), ToolError> {
    let with_source = |e: ToolError| match e {
        ToolError::Refused { why, .. } => ToolError::Drive(format!(
            "{source}: the drive refused the configuration: {why}"
        )),
        e => e,
    };
    for (f, v) in values {
        link.acked(&Request::ConfigSet {
            key: f.key(),
            value_bits: v.to_bits(),
        })
        .map_err(|e| match e {
            ToolError::Refused { why, .. } => ToolError::Drive(format!(
                "{source}: {} = {v}: the drive refused it: {why}",
                f.name()
            )),
            e => e,
        })?;
    }
    // The drive converts no units: the image of the staged values is built here.
    let image = read_settings(link, true)?.parts_image().map_err(|e| {
        ToolError::Drive(format!(
            "{source}: the configuration is refused: {}",
            with_unit(&e)
        ))
    })?;
    for req in config_parts_requests(&image) {
        link.acked(&req).map_err(with_source)?;
    }
    link.acked(&Request::ConfigApply).map_err(with_source)
}

/// A flat TOML table of `name = value`: quoted dotted names (`"rig.gear_ratio" = 19.2`), dotted
/// keys (`rig.gear_ratio = 19.2`) and `[rig]` sections are the same thing. Errors name the file
/// and the field.
pub fn parse_file(path: &Path, text: &str) -> Result<Vec<(&'static Field, f64)>, ToolError> {
    let file = |reason: String| ToolError::file(path.display(), reason);
    // One line with the place, not the parser's multi-line echo of the input.
    let table: toml::Table = hil_sim::input::from_toml(text).map_err(|e| file(e.to_string()))?;
    let mut flat = Vec::new();
    flatten("", &table, &mut flat);
    let mut out: Vec<(&'static Field, f64)> = Vec::new();
    for (name, value) in flat {
        let field = lookup(&name).map_err(|e| file(e.to_string()))?;
        let v = match value {
            toml::Value::Float(x) => x,
            toml::Value::Integer(i) => i as f64,
            toml::Value::Boolean(b) if field.whole => b as u8 as f64,
            other => {
                return Err(file(format!(
                    "{name}: {} is not a number ({})",
                    other, field.unit
                )))
            }
        };
        check(field, v).map_err(|e| file(e.to_string()))?;
        if out.iter().any(|(f, _)| f.key() == field.key()) {
            return Err(file(format!("{name}: given twice")));
        }
        out.push((field, v));
    }
    if out.is_empty() {
        return Err(file("no configuration values in the file".into()));
    }
    out.sort_by_key(|(f, _)| f.key());
    Ok(out)
}

fn flatten(prefix: &str, table: &toml::Table, out: &mut Vec<(String, toml::Value)>) {
    for (k, v) in table {
        let name = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match v {
            toml::Value::Table(t) => flatten(&name, t, out),
            v => out.push((name, v.clone())),
        }
    }
}

/// A value as written in a dump: whole fields as integers, others exactly (Rust's shortest
/// round-trip form), always readable back as the same `f64`.
pub fn format_value(field: &Field, v: f64) -> String {
    if field.whole && v.is_finite() && v.abs() < 1e15 {
        format!("{}", v as i64)
    } else if v.is_finite() {
        format!("{v:?}")
    } else {
        // TOML spells them so; the drive refuses them anyway.
        if v.is_nan() {
            "nan".into()
        } else if v > 0.0 {
            "inf".into()
        } else {
            "-inf".into()
        }
    }
}

/// The active configuration as a file `config load` reads back.
pub fn dump(port: &str, values: &[FieldValue]) -> String {
    let mut s = format!(
        "# belt-drive configuration read from {port} (active values)\n\
         # load with: beltctl --port PATH config load FILE\n"
    );
    for v in values {
        s.push_str(&format!(
            "{:<48} # {}\n",
            format!(
                "\"{}\" = {}",
                v.field.name(),
                format_value(v.field, v.active)
            ),
            v.field.unit
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err<T>(r: Result<T, impl std::fmt::Display>) -> String {
        match r {
            Ok(_) => panic!("accepted"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn files_flatten_names_and_refuse_by_name() {
        let p = Path::new("rig.toml");
        let vals = parse_file(
            p,
            "\"rig.gear_ratio\" = 19.2\ndrive.rate_hz = 4000\n[homing]\ntowards_positive = true\n",
        )
        .unwrap();
        let names: Vec<_> = vals.iter().map(|(f, v)| (f.name(), *v)).collect();
        assert!(names.contains(&("rig.gear_ratio", 19.2)));
        assert!(names.contains(&("drive.rate_hz", 4000.0)));
        assert!(names.contains(&("homing.towards_positive", 1.0)));

        let e = err(parse_file(p, "rig.gear_ration = 1\n"));
        assert!(e.starts_with("rig.toml: rig.gear_ration: no such configuration field; did you mean rig.encoder_lines, rig.gear_ratio"), "{e}");
        let e = err(parse_file(p, "rig.encoder_lines = 1.5\n"));
        assert!(
            e.contains("rig.toml: rig.encoder_lines: out of range"),
            "{e}"
        );
        let e = err(parse_file(p, "rig.gear_ratio = \"fast\"\n"));
        assert!(
            e.contains("rig.toml: rig.gear_ratio: \"fast\" is not a number"),
            "{e}"
        );
        let e = err(parse_file(
            p,
            "\"rig.pulley_teeth\" = 20\nrig.pulley_teeth = 20\n",
        ));
        assert!(e.contains("given twice"), "{e}");
        let e = err(parse_file(p, "rig.gear_ratio = \n"));
        assert!(e.starts_with("rig.toml: "), "{e}");
    }

    #[test]
    fn a_dump_loads_back_to_the_same_values() {
        let values: Vec<FieldValue> = FIELDS
            .iter()
            .map(|f| {
                let v = Settings::PAPER.get(f.key()).unwrap();
                FieldValue {
                    field: f,
                    active: if f.whole { v } else { v / 3.0 },
                    staged: v,
                }
            })
            .collect();
        let text = dump("/dev/x", &values);
        let back = parse_file(Path::new("dump.toml"), &text).unwrap();
        assert_eq!(back.len(), FIELDS.len());
        for ((f, v), want) in back.iter().zip(&values) {
            assert_eq!(f.key(), want.field.key());
            assert_eq!(v.to_bits(), want.active.to_bits(), "{}", f.name());
        }
    }

    #[test]
    fn a_refused_configuration_leaves_the_staged_values_as_they_were() {
        let mut link = crate::testing::endpoint_drive(|_| false);
        let name = |n: &str| lookup(n).unwrap();
        let travel = name("drive.travel_max_mm");
        let kp = name("pid.kp_a_per_mm");
        let was = get(&mut link, travel).unwrap();
        // A travel that ends before it starts: refused when the image is built.
        let e = set_and_apply(&mut link, &[(kp, 12.0), (travel, -5.0)], "t.toml")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("t.toml: the configuration is refused: "),
            "{e}"
        );
        assert!(
            e.ends_with("nothing changed (the staged values put back)"),
            "{e}"
        );
        for f in [travel, kp] {
            let v = get(&mut link, f).unwrap();
            assert_eq!(v.staged_change(), None, "{}", f.name());
        }
        assert_eq!(get(&mut link, travel).unwrap().active, was.active);
        // A good change still applies after it.
        set_and_apply(&mut link, &[(kp, 12.0)], "t.toml").unwrap();
        assert_eq!(get(&mut link, kp).unwrap().active, 12.0);
    }

    #[test]
    fn assignments() {
        let (f, v) = parse_assignment("polarity.scale_inverted=true").unwrap();
        assert_eq!((f.name(), v), ("polarity.scale_inverted", 1.0));
        assert!(err(parse_assignment("rig.gear_ratio")).contains("NAME=VALUE"));
        assert!(err(parse_assignment("drive.initial_model=9"))
            .contains("drive.initial_model: out of range"));
        assert!(matches!(
            parse_assignment("drive.initial_model=9"),
            Err(ArgError::Refused { unit, whole: true, .. }) if !unit.is_empty()
        ));
        assert!(matches!(
            parse_assignment("rig.gear_ratio=x"),
            Err(ArgError::NotANumber {
                field: "rig.gear_ratio",
                ..
            })
        ));
        match lookup("rig.gear") {
            Err(ArgError::UnknownNear { near, .. }) => assert!(near.contains(&"rig.gear_ratio")),
            Err(other) => panic!("{other:?}"),
            Ok(f) => panic!("rig.gear found {}", f.name()),
        }
        assert!(matches!(
            lookup("zzz"),
            Err(ArgError::Unknown { name }) if name == "zzz"
        ));
    }
}
