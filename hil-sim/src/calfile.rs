//! Calibration on disk: `calibration.bin` (the blob; the drive loads the image built from it)
//! and `calibration.toml` (the same parameters for people, plus the baselines and the fit
//! quality).

use std::path::{Path, PathBuf};

use estimator_core::blob::{self, BlobError};
use estimator_core::model::ModelParams;
use estimator_core::rig::Rig;
use serde::Serialize;

use crate::calibrate::Calibration;
use crate::coverage::Coverage;

/// The human-readable file.
#[derive(Serialize)]
struct CalFile {
    note: String,
    fit_rms_um: toml::Table,
    /// What the recordings covered (see `crate::coverage`); not in the blob.
    #[serde(skip_serializing_if = "Option::is_none")]
    coverage: Option<toml::Table>,
    #[serde(flatten)]
    models: Models,
}

/// The model sections: a copy of what `calibration.bin` holds, for people to read.
#[derive(Serialize)]
struct Models {
    reversal_deadband_counts: u32,
    model1: toml::Table,
    model2: toml::Table,
    model3: toml::Table,
    model4: toml::Table,
    backlash: toml::Table,
    bidir_table: toml::Table,
}

fn table(pairs: &[(&str, f64)]) -> toml::Table {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), toml::Value::Float(*v)))
        .collect()
}

fn floats(v: &[f64]) -> toml::Value {
    toml::Value::Array(
        v.iter()
            .map(|x| toml::Value::Float((x * 1e4).round() / 1e4))
            .collect(),
    )
}

/// Why a calibration directory could not be written or read; every case names the file.
#[derive(Debug, thiserror::Error)]
pub enum CalFileError {
    /// The file system refused (missing directory, permissions, a full disk).
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// `calibration.bin` was made for another drive-train geometry.
    #[error("{}: calibrated for {made_for}; this plant has {plant}: calibrate again on it", path.display())]
    OtherGeometry {
        /// The blob.
        path: PathBuf,
        /// The geometry the blob records.
        made_for: Rig,
        /// The geometry it was loaded for.
        plant: Rig,
    },
    /// The blob is damaged, of another version, or holds a parameter out of range.
    #[error("{}: {source}", path.display())]
    Blob {
        /// The blob.
        path: PathBuf,
        /// The reason, naming the field where there is one.
        source: BlobError,
    },
    /// `calibration.toml` does not parse.
    #[error("{}: {source}", path.display())]
    Toml {
        /// The TOML file.
        path: PathBuf,
        /// Where and why.
        source: crate::input::TomlError,
    },
    /// The calibration could not be written as TOML.
    #[error("{}: not written as TOML: {source}", path.display())]
    ToToml {
        /// The TOML file.
        path: PathBuf,
        /// What the serialiser said.
        source: toml::ser::Error,
    },
    /// `calibration.toml` lacks its `[fit_rms_um]` table.
    #[error("{}: [fit_rms_um] is missing", path.display())]
    MissingFitRms {
        /// The TOML file.
        path: PathBuf,
    },
    /// One model's fit quality is absent, negative or not a number.
    #[error("{}: fit_rms_um.{model} is missing or not a finite number >= 0", path.display())]
    BadFitRms {
        /// The TOML file.
        path: PathBuf,
        /// The model's key.
        model: &'static str,
    },
    /// The `[coverage]` table is malformed.
    #[error("{}: {field}", path.display())]
    BadCoverage {
        /// The TOML file.
        path: PathBuf,
        /// The field and what it must hold.
        field: String,
    },
    /// The model sections were edited: the drive loads the blob, so the edit would be ignored.
    #[error(
        "{}: {field} differs from {}: the drive loads the blob, so edits to the model sections \
         are not used; run `hil-sim calibrate` again (or restore the file)",
        path.display(),
        blob.display()
    )]
    Edited {
        /// The TOML file.
        path: PathBuf,
        /// The first differing field, with both values.
        field: String,
        /// The blob it must match.
        blob: PathBuf,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CalFileError + '_ {
    move |source| CalFileError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Checks that `dir` can be made and written, and leaves nothing behind: what a calibration
/// checks before it records anything, so that a bad `--out` is refused before minutes of moves,
/// not after them.
pub fn check_writable(dir: &Path) -> Result<(), CalFileError> {
    // The outermost directory this makes, removed again afterwards.
    let mut made = None;
    let mut p = dir;
    while !p.as_os_str().is_empty() && std::fs::symlink_metadata(p).is_err() {
        made = Some(p);
        p = p.parent().unwrap_or(Path::new(""));
    }
    let result = (|| {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let probe = dir.join(format!(".write-test-{}", std::process::id()));
        std::fs::write(&probe, b"").map_err(io(dir))?;
        std::fs::remove_file(&probe).map_err(io(&probe))
    })();
    if let Some(top) = made {
        let _ = std::fs::remove_dir_all(top);
    }
    result
}

/// Writes both files into `dir`; the parameters are those of the blob (quantised).
pub fn save(dir: &Path, cal: &Calibration, rig: &Rig) -> Result<(), CalFileError> {
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let bin = dir.join("calibration.bin");
    let blob_err = |source| CalFileError::Blob {
        path: bin.clone(),
        source,
    };
    let mut buf = vec![0u8; blob::MAX_BYTES];
    let n = blob::encode(&cal.params, rig, &mut buf).map_err(blob_err)?;
    std::fs::write(&bin, &buf[..n]).map_err(io(&bin))?;
    let p = blob::decode(&buf[..n], rig).map_err(blob_err)?;
    let file = CalFile {
        note: format!(
            "belt-drive calibration from {} samples; units in the names; the drive loads the \
             coefficients built from calibration.bin ({n} bytes), which holds the model sections \
             below: edit neither by hand (a calibration.toml that no longer matches its \
             calibration.bin is refused); [coverage] is the region the calibration moves covered, \
             for warnings only (not in calibration.bin)",
            cal.samples
        ),
        fit_rms_um: cal
            .fit_rms_um
            .iter()
            .map(|(k, v)| (k.as_str().to_string(), toml::Value::Float(*v)))
            .collect(),
        coverage: cal.coverage.as_ref().map(|c| c.to_toml()),
        models: models_of(&p),
    };
    let path = dir.join("calibration.toml");
    let text = toml::to_string(&file).map_err(|source| CalFileError::ToToml {
        path: path.clone(),
        source,
    })?;
    std::fs::write(&path, text).map_err(io(&path))
}

/// The model sections of `calibration.toml` for parameters `p` (as the blob holds them).
fn models_of(p: &ModelParams) -> Models {
    let (m1, m2, m3) = (&p.model1, &p.model2, &p.model3);
    let mut model3 = toml::Table::new();
    for (name, b) in [
        ("forward_band", &m3.forward_band),
        ("reverse_band", &m3.reverse_band),
    ] {
        let mut t = toml::Table::new();
        t.insert("x_mm".into(), floats(&b.x_mm[..b.len]));
        t.insert("y_um".into(), floats(&b.y_um[..b.len]));
        model3.insert(name.into(), toml::Value::Table(t));
    }
    for (name, tr) in [
        ("forward_transition", &m3.forward_transition),
        ("reverse_transition", &m3.reverse_transition),
    ] {
        let mut t = table(&[("d_step_mm", tr.d_step_mm), ("g0_step_um", tr.g0_step_um)]);
        let rows = tr
            .gap_um
            .iter()
            .take(tr.n_d)
            .map(|r| floats(&r[..tr.n_g0]))
            .collect();
        t.insert("gap_um".into(), toml::Value::Array(rows));
        model3.insert(name.into(), toml::Value::Table(t));
    }
    Models {
        reversal_deadband_counts: p.reversal_deadband_counts,
        model1: table(&[
            ("m_mm_per_mm", m1.m_mm_per_mm),
            ("offset_mm", m1.offset_mm),
            ("h_mm", m1.h_mm),
            ("h_g_mm", m1.h_g_mm),
            ("slope_a_mm_per_mm", m1.slope_a_mm_per_mm),
            ("slope_b_mm_per_mm", m1.slope_b_mm_per_mm),
        ]),
        model2: table(&[
            ("m_mm_per_mm", m2.m_mm_per_mm),
            ("offset_mm", m2.offset_mm),
            ("h_mm", m2.h_mm),
            ("h_g_mm", m2.h_g_mm),
            ("rate_a_per_mm", m2.rate_a_per_mm),
            ("rate_b_per_mm", m2.rate_b_per_mm),
            ("amplitude_a_mm", m2.amplitude_a_mm),
            ("amplitude_b_mm", m2.amplitude_b_mm),
        ]),
        model3,
        model4: {
            let m = &p.model4;
            let mut t = table(&[
                ("x_ref_mm", m.x_ref_mm),
                ("offset_um", m.offset_um),
                ("slope_um_per_mm", m.slope_um_per_mm),
                ("knot_start_mm", m.knot_start_mm),
                ("knot_step_mm", m.knot_step_mm),
                ("pitch_mm", m.pitch_mm),
                ("turn_mm", m.turn_mm),
                ("current_um_per_a", m.current_um_per_a),
                ("current_lp_um_per_a", m.current_lp_um_per_a),
            ]);
            for (k, v) in [
                ("widths_mm", &m.widths_mm[..]),
                ("play_um_per_mm", &m.play_um_per_mm[..]),
                ("play_forward_um_per_mm", &m.play_forward_um_per_mm[..]),
                ("knot_um", &m.knot_um[..]),
                ("pitch_um", &m.pitch_um[..]),
                ("turn_um", &m.turn_um[..]),
            ] {
                t.insert(k.into(), floats(v));
            }
            // The slip observer: the belt's tooth gap, its load and creep as fitted.
            let sl = &m.slip;
            let mut slip = table(&[
                ("creep_per_mm", sl.creep_per_mm),
                ("limit_um", sl.limit_um),
                ("half_gap_um", sl.half_gap_um),
                ("weight", sl.weight),
            ]);
            slip.insert("load_um".into(), floats(&sl.load_um));
            slip.insert("um_per_a".into(), floats(&sl.um_per_a));
            t.insert("slip".into(), toml::Value::Table(slip));
            // The belt observer in the slip observer's place, where the calibration has one:
            // its identified physics (SI), the step and the weight.
            if let Some(b) = &m.belt {
                let p = &b.physics;
                let mut belt = table(&[
                    ("tick_s", b.tick_s),
                    ("step_ticks", f64::from(b.step_ticks)),
                    ("weight", b.weight),
                    ("fast_share", b.fast_share),
                    ("mass_kg", p.mass_kg),
                    ("guide_n", p.guide_n),
                    ("preload_n", p.preload_n),
                    ("axial_rigidity_n", p.axial_rigidity_n),
                    ("length_m", p.length_m),
                    ("span_offset_m", p.span_offset_m),
                    ("wrap_rad", p.wrap_rad),
                    ("sigma0_per_m", p.sigma0_per_m),
                    ("sigma1_s_per_m", p.sigma1_s_per_m),
                    ("sigma2_s_per_m", p.sigma2_s_per_m),
                    ("mu_static", p.mu_static),
                    ("mu_kinetic", p.mu_kinetic),
                    ("stribeck_m_per_s", p.stribeck_m_per_s),
                    ("kappa_per_m", p.kappa_per_m),
                    ("half_gap_m", p.half_gap_m),
                    ("tooth_n_per_m", p.tooth_n_per_m),
                    ("gear_half_m", p.gear_half_m),
                    ("gear_n_per_m", p.gear_n_per_m),
                    ("span_damping_n_s_per_m", p.span_damping_n_s_per_m),
                    ("accel_per_a", p.accel_per_a),
                    ("m_per_count", p.m_per_count),
                    ("track_discount", p.track_discount),
                    ("guide_profile_start_m", p.guide_start_m),
                    ("guide_profile_step_m", p.guide_step_m),
                ]);
                belt.insert("rest_um".into(), floats(&b.rest_um));
                belt.insert(
                    "half_travel_mm".into(),
                    toml::Value::Array(b.half_travel_mm.map(toml::Value::Float).to_vec()),
                );
                let guide = p.guide_delta_n[..p.guide_bins.min(p.guide_delta_n.len())]
                    .iter()
                    .map(|&v| toml::Value::Float(v))
                    .collect();
                belt.insert("guide_profile_n".into(), toml::Value::Array(guide));
                t.insert("belt".into(), toml::Value::Table(belt));
            }
            t
        },
        backlash: table(&[
            ("offset_um", p.backlash.offset_um),
            ("backlash_um", p.backlash.backlash_um),
        ]),
        bidir_table: {
            let b = &p.bidir_table;
            let mut t = table(&[("x0_mm", b.x0_mm), ("step_mm", b.step_mm)]);
            t.insert("forward_um".into(), floats(&b.forward_um[..b.rows]));
            t.insert("reverse_um".into(), floats(&b.reverse_um[..b.rows]));
            t
        },
    }
}

/// The first place where `found` (the file) differs from `want` (the blob), as a dotted path.
fn first_difference(path: &str, want: &toml::Value, found: &toml::Value) -> Option<String> {
    use toml::Value as V;
    match (want, found) {
        (V::Table(w), V::Table(f)) => {
            if let Some(k) = f.keys().find(|k| !w.contains_key(*k)) {
                return Some(format!("{path}.{k} (not a calibration field)"));
            }
            w.iter().find_map(|(k, wv)| match f.get(k) {
                None => Some(format!("{path}.{k} (missing)")),
                Some(fv) => first_difference(&format!("{path}.{k}"), wv, fv),
            })
        }
        (V::Array(w), V::Array(f)) => {
            if w.len() != f.len() {
                return Some(format!(
                    "{path} ({} entries, calibration.bin has {})",
                    f.len(),
                    w.len()
                ));
            }
            w.iter()
                .zip(f)
                .enumerate()
                .find_map(|(i, (wv, fv))| first_difference(&format!("{path}[{i}]"), wv, fv))
        }
        (V::Float(w), V::Float(f)) if w == f => None,
        (V::Float(w), V::Integer(f)) if *w == *f as f64 => None,
        (V::Integer(w), V::Integer(f)) if w == f => None,
        (w, f) => Some(format!("{path} = {f} (calibration.bin: {w})")),
    }
}

/// Reads a calibration directory: the blob (checked as the firmware checks it; it holds every
/// compensator, the baselines included) and the fit quality from the TOML file.
pub fn load(dir: &Path, rig: &Rig) -> Result<Calibration, CalFileError> {
    let bin = dir.join("calibration.bin");
    let bytes = crate::input::read_file(&bin).map_err(io(&bin))?;
    let params: ModelParams = blob::decode(&bytes, rig).map_err(|source| {
        // Say which geometries differ: the blob records the geometry it was made for.
        match (source, blob::calibrated_rig(&bytes)) {
            (BlobError::RigMismatch, Ok(made_for)) => CalFileError::OtherGeometry {
                path: bin.clone(),
                made_for,
                plant: *rig,
            },
            (source, _) => CalFileError::Blob {
                path: bin.clone(),
                source,
            },
        }
    })?;
    let path = dir.join("calibration.toml");
    let text = crate::input::read_text(&path).map_err(io(&path))?;
    let mut found: toml::Table =
        crate::input::from_toml(&text).map_err(|source| CalFileError::Toml {
            path: path.clone(),
            source,
        })?;
    found.remove("note");
    let fit_rms_um = match found.remove("fit_rms_um") {
        Some(toml::Value::Table(t)) => t,
        _ => return Err(CalFileError::MissingFitRms { path }),
    };
    let coverage = match found.remove("coverage") {
        None => None,
        Some(toml::Value::Table(t)) => {
            Some(
                Coverage::from_toml(&t).map_err(|field| CalFileError::BadCoverage {
                    path: path.clone(),
                    field,
                })?,
            )
        }
        Some(_) => {
            return Err(CalFileError::BadCoverage {
                path,
                field: "coverage: not a table".into(),
            })
        }
    };
    // The model sections mirror the blob: an edit there would be silently ignored, so it is
    // refused instead, naming the field.
    let want =
        toml::Value::try_from(models_of(&params)).map_err(|source| CalFileError::ToToml {
            path: path.clone(),
            source,
        })?;
    let found = toml::Value::Table(found);
    if let Some(at) = first_difference("", &want, &found) {
        return Err(CalFileError::Edited {
            path,
            field: at.trim_start_matches('.').to_string(),
            blob: bin,
        });
    }
    let rms = |k: &'static str| match fit_rms_um.get(k).and_then(|v| v.as_float()) {
        Some(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(CalFileError::BadFitRms {
            path: path.clone(),
            model: k,
        }),
    };
    use estimator_core::model::ModelKind as K;
    Ok(Calibration {
        params,
        fit_rms_um: [
            (K::Linear, rms("model1")?),
            (K::Exponential, rms("model2")?),
            (K::Table, rms("model3")?),
            (K::Operator, rms("model4")?),
        ],
        samples: 0,
        coverage,
    })
}
