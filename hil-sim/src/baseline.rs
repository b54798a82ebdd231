//! What machine builders use today (see shared/ANCHORS.md), calibrated from the same data as the
//! paper's models so that the comparison is fair:
//! - `Backlash`: constant backlash compensation in the Marlin `M425` / LinuxCNC `BACKLASH` style:
//!   one offset and one backlash per axis, switched by the commanded direction.
//! - `BidirTable`: a bidirectional position table in the LinuxCNC `COMP_FILE` style: up to 256
//!   rows of (position, forward error, reverse error), linear interpolation, direction from the
//!   commanded velocity, no model of the passage between the two curves.
//!
//! This module measures them; the drive runs them (`estimator_core::model::baseline`), in fixed
//! point like the paper's models, selectable at run time as `backlash` and `bidir_table`.
//!
//! Both are measured the way their users measure them: from samples taken after a run-up of
//! `RUN_UP_MM` in the direction of approach, as a dial indicator or a G425 probe would.

use crate::run::Trace;

/// Run-up in the direction of approach before a sample counts as "approached from" that side.
pub const RUN_UP_MM: f64 = 5.0;
/// LinuxCNC's compensation file holds at most 256 rows; so does the drive's table.
pub const MAX_ROWS: usize = estimator_core::model::MAX_BIDIR_ROWS;

/// Per-record commanded direction and the motor travel since that direction was taken.
fn run_up(trace: &Trace) -> Vec<(i8, f64)> {
    let mut out = Vec::with_capacity(trace.records.len());
    let mut dir = 0i8;
    let mut since = 0.0f64;
    let mut prev = trace.x_pe_mm(0);
    for (i, r) in trace.records.iter().enumerate() {
        let x = trace.x_pe_mm(i);
        if r.cmd_dir != dir {
            dir = r.cmd_dir;
            since = 0.0;
        } else {
            since += (x - prev).abs();
        }
        prev = x;
        out.push((dir, since));
    }
    out
}

/// Constant backlash compensation.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Backlash {
    /// Mean of the two directions' errors, um.
    pub offset_um: f64,
    /// Reverse minus forward error, um (what `M425` would be set to).
    pub backlash_um: f64,
}

impl Backlash {
    /// Measures offset and backlash from approached samples of every trace.
    pub fn calibrate(traces: &[Trace]) -> Option<Backlash> {
        let (mut sf, mut nf, mut sr, mut nr) = (0.0, 0usize, 0.0, 0usize);
        for tr in traces {
            for (i, (dir, since)) in run_up(tr).into_iter().enumerate() {
                if since < RUN_UP_MM {
                    continue;
                }
                if dir > 0 {
                    sf += tr.dx_um(i);
                    nf += 1;
                } else if dir < 0 {
                    sr += tr.dx_um(i);
                    nr += 1;
                }
            }
        }
        if nf == 0 || nr == 0 {
            return None;
        }
        let (f, r) = (sf / nf as f64, sr / nr as f64);
        Some(Backlash {
            offset_um: 0.5 * (f + r),
            backlash_um: r - f,
        })
    }
}

/// Bidirectional position-error table.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BidirTable {
    /// Position of the first row, mm.
    pub x0_mm: f64,
    /// Row spacing, mm.
    pub step_mm: f64,
    /// Forward (increasing position) error per row, um.
    pub forward_um: Vec<f64>,
    /// Reverse error per row, um.
    pub reverse_um: Vec<f64>,
}

fn fill_gaps(sum: &[f64], n: &[usize]) -> Option<Vec<f64>> {
    let known: Vec<(usize, f64)> = (0..sum.len())
        .filter(|&i| n[i] > 0)
        .map(|i| (i, sum[i] / n[i] as f64))
        .collect();
    if known.is_empty() {
        return None;
    }
    Some(
        (0..sum.len())
            .map(|i| match known.binary_search_by(|(k, _)| k.cmp(&i)) {
                Ok(j) => known[j].1,
                Err(0) => known[0].1,
                Err(j) if j == known.len() => known[j - 1].1,
                Err(j) => {
                    let (a, ya) = known[j - 1];
                    let (b, yb) = known[j];
                    ya + (yb - ya) * (i - a) as f64 / (b - a) as f64
                }
            })
            .collect(),
    )
}

impl BidirTable {
    /// Bins approached samples by position into at most `rows` rows per direction.
    pub fn calibrate(traces: &[Trace], rows: usize) -> Option<BidirTable> {
        let rows = rows.clamp(2, MAX_ROWS);
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for tr in traces {
            for i in 0..tr.records.len() {
                let x = tr.x_pe_mm(i);
                lo = lo.min(x);
                hi = hi.max(x);
            }
        }
        if hi <= lo {
            return None;
        }
        let step = (hi - lo) / (rows - 1) as f64;
        let (mut sf, mut nf) = (vec![0.0; rows], vec![0usize; rows]);
        let (mut sr, mut nr) = (vec![0.0; rows], vec![0usize; rows]);
        for tr in traces {
            for (i, (dir, since)) in run_up(tr).into_iter().enumerate() {
                if since < RUN_UP_MM || dir == 0 {
                    continue;
                }
                let row = (((tr.x_pe_mm(i) - lo) / step).round() as usize).min(rows - 1);
                if dir > 0 {
                    sf[row] += tr.dx_um(i);
                    nf[row] += 1;
                } else {
                    sr[row] += tr.dx_um(i);
                    nr[row] += 1;
                }
            }
        }
        Some(BidirTable {
            x0_mm: lo,
            step_mm: step,
            forward_um: fill_gaps(&sf, &nf)?,
            reverse_um: fill_gaps(&sr, &nr)?,
        })
    }
}

impl Backlash {
    /// The drive's parameters.
    pub fn to_params(&self) -> estimator_core::model::BacklashParams {
        estimator_core::model::BacklashParams {
            offset_um: self.offset_um,
            backlash_um: self.backlash_um,
        }
    }
}

impl BidirTable {
    /// The drive's parameters (at most [`MAX_ROWS`] rows, as `calibrate` makes them).
    pub fn to_params(&self) -> estimator_core::model::BidirParams {
        let mut p = estimator_core::model::BidirParams::ZERO;
        let rows = self
            .forward_um
            .len()
            .min(self.reverse_um.len())
            .min(MAX_ROWS);
        p.rows = rows;
        p.x0_mm = self.x0_mm;
        p.step_mm = self.step_mm;
        p.forward_um[..rows].copy_from_slice(&self.forward_um[..rows]);
        p.reverse_um[..rows].copy_from_slice(&self.reverse_um[..rows]);
        p
    }
}
