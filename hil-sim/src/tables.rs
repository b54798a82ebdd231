//! Model 3's tables measured from recorded (x_PE, x_LS) samples, the way the paper builds them
//! from Fig. 15-type reversal runs: per-direction band tables along travel and per-direction 2-D
//! transition tables of the remaining gap after a reversal.
//!
//! Parametrisation (estimator-core's Model 3): after a reversal at the turning point x_d, the error
//! is y = band_new(x) + s * G(d, g0), with d = |x - x_d| the travel since the turning point,
//! g0 = |y_turn - band_new(x_d)| the gap to the new band edge at the turning point and s the side
//! of the band the new edge lies on. G is fitted by regularised linear least squares on a bilinear
//! grid, with G(0, g0) imposed strongly (g0 less the linear model's fast jump h_g, as eq. 16).

use estimator_core::model::{self, Direction, ModelKind, ModelParams, ModelState};
use estimator_core::rig::Rig;

/// A stroke between two reversals, found with the drive's own reversal rule.
#[derive(Clone, Debug, PartialEq)]
pub struct Stroke {
    /// +1 forward (increasing x), -1 reverse.
    pub dir: i8,
    /// Turning point the stroke starts from, counts.
    pub x_turn_counts: i32,
    /// Record index of the turning point.
    pub turn_index: usize,
    /// Records of the stroke: `start..end`.
    pub start: usize,
    /// End (exclusive).
    pub end: usize,
}

/// Splits a motor-position sequence into strokes with the drive's own reversal detector
/// ([`ModelState`]: a reversal is registered once the position has moved more than
/// `deadband_counts` back from the extreme reached in the current direction; the turning point is
/// that extreme), so calibration sees exactly the reversals the firmware will register.
/// The first stroke is forward, as the detector starts.
pub fn strokes(x_counts: &[i32], deadband_counts: u32) -> Vec<Stroke> {
    let mut out = Vec::new();
    let Some(&x0) = x_counts.first() else {
        return out;
    };
    let params = ModelParams {
        reversal_deadband_counts: deadband_counts,
        ..ModelParams::PAPER
    };
    let Ok(coeffs) = params.build(&Rig::PAPER) else {
        return out;
    };
    let mut state = ModelState::new(x0);
    let dir_of = |s: &ModelState| {
        if s.direction() == Direction::Forward {
            1
        } else {
            -1
        }
    };
    let (mut dir, mut start, mut turn) = (1i8, 0usize, (x0, 0usize));
    for (i, &x) in x_counts.iter().enumerate() {
        model::estimate(&coeffs, ModelKind::None, &mut state, x);
        if dir_of(&state) != dir {
            out.push(Stroke {
                dir,
                x_turn_counts: turn.0,
                turn_index: turn.1,
                start,
                end: i,
            });
            let x_turn = state.turning_point_counts();
            // The extreme was reached within this stroke: the last record standing on it.
            let at = (start..i)
                .rev()
                .find(|&k| x_counts[k] == x_turn)
                .unwrap_or(start);
            (dir, start, turn) = (-dir, i, (x_turn, at));
        }
    }
    out.push(Stroke {
        dir,
        x_turn_counts: turn.0,
        turn_index: turn.1,
        start,
        end: x_counts.len(),
    });
    out
}

/// The normal equations of a linear least-squares fit, accumulated row by row (the probes'
/// fits in `examples/`).
#[derive(Clone, Debug)]
pub struct NormalEquations {
    ata: Vec<f64>,
    atb: Vec<f64>,
    yy: f64,
}

impl NormalEquations {
    /// No rows yet, `n` unknowns.
    pub fn new(n: usize) -> NormalEquations {
        NormalEquations {
            ata: vec![0.0; n * n],
            atb: vec![0.0; n],
            yy: 0.0,
        }
    }

    /// One observation `y` of `row . w` (`row` has the `n` columns).
    pub fn add(&mut self, row: &[f64], y: f64) {
        let n = self.atb.len();
        self.yy += y * y;
        for (i, &ri) in row.iter().enumerate().take(n) {
            if ri != 0.0 {
                self.atb[i] += ri * y;
                for (a, &rj) in self.ata[i * n..(i + 1) * n].iter_mut().zip(row) {
                    *a += ri * rj;
                }
            }
        }
    }

    /// The weights and the residual sum of squares, with a ridge of `ridge` times each diagonal
    /// entry (plus 1e-9) against columns the rows hardly reach; `None` if still singular.
    pub fn solve(mut self, ridge: f64) -> Option<(Vec<f64>, f64)> {
        let n = self.atb.len();
        for i in 0..n {
            self.ata[i * n + i] += ridge * self.ata[i * n + i] + 1e-9;
        }
        let atb = self.atb.clone();
        let w = solve_spd(self.ata, self.atb)?;
        let sse = self.yy - w.iter().zip(&atb).map(|(p, q)| p * q).sum::<f64>();
        Some((w, sse))
    }
}

/// Normal equations of fixed columns, solved again and again with one more column beside them
/// (a state whose parameters a search varies, fitted jointly with the fixed terms' weights).
#[derive(Clone, Debug)]
pub struct Bordered(NormalEquations);

impl Bordered {
    /// No rows yet, `n` fixed columns.
    pub fn new(n: usize) -> Bordered {
        Bordered(NormalEquations::new(n))
    }

    /// One observation `y` of the fixed columns `row`.
    pub fn add(&mut self, row: &[f64], y: f64) {
        self.0.add(row, y);
    }

    /// The weights (the extra column's last) and the residual sum, with `rows` the same
    /// observations as added, in order, each with its extra column's value: `(row, y, extra)`.
    /// A ridge of 1e-6 of each diagonal entry plus 1e-9; `None` if still singular.
    pub fn solve_with<'a>(
        &self,
        rows: impl Iterator<Item = (&'a [f64], f64, f64)>,
    ) -> Option<(Vec<f64>, f64)> {
        let fixed = &self.0;
        let n = fixed.atb.len();
        let m = n + 1;
        let mut a = vec![0.0; m * m];
        for i in 0..n {
            a[i * m..i * m + n].copy_from_slice(&fixed.ata[i * n..(i + 1) * n]);
        }
        let mut b = fixed.atb.clone();
        b.push(0.0);
        for (row, y, c) in rows {
            for (i, &ri) in row.iter().enumerate().take(n) {
                a[i * m + n] += ri * c;
            }
            a[n * m + n] += c * c;
            b[n] += c * y;
        }
        for i in 0..n {
            a[n * m + i] = a[i * m + n];
        }
        for i in 0..m {
            a[i * m + i] += 1e-6 * a[i * m + i] + 1e-9;
        }
        let rhs = b.clone();
        let w = solve_spd(a, b)?;
        let sse = fixed.yy - w.iter().zip(&rhs).map(|(p, q)| p * q).sum::<f64>();
        Some((w, sse))
    }
}

/// Solves the symmetric positive definite system `a x = b` (row-major n x n) by Cholesky.
pub fn solve_spd(mut a: Vec<f64>, mut b: Vec<f64>) -> Option<Vec<f64>> {
    let n = b.len();
    if a.len() != n * n {
        return None;
    }
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if d.is_nan() || d <= 0.0 {
            return None;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
    }
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= a[i * n + k] * b[k];
        }
        b[i] = s / a[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in i + 1..n {
            s -= a[k * n + i] * b[k];
        }
        b[i] = s / a[i * n + i];
    }
    Some(b)
}

/// Index of the cell of a strictly increasing axis containing `v` and the weight of the upper
/// node (clamped to the axis).
pub fn cell(axis: &[f64], v: f64) -> (usize, f64) {
    let n = axis.len();
    if v <= axis[0] {
        return (0, 0.0);
    }
    if v >= axis[n - 1] {
        return (n - 2, 1.0);
    }
    let j = axis.partition_point(|&a| a <= v).clamp(1, n - 1) - 1;
    (j, (v - axis[j]) / (axis[j + 1] - axis[j]))
}

/// Linear interpolation on an axis (clamped).
pub fn interp(axis: &[f64], values: &[f64], v: f64) -> f64 {
    let (j, w) = cell(axis, v);
    values[j] * (1.0 - w) + values[j + 1] * w
}

/// One observation of the gap after a reversal.
#[derive(Clone, Copy, Debug)]
pub struct GapSample {
    /// Travel since the turning point, mm.
    pub d_mm: f64,
    /// Gap to the new band edge at the turning point, um.
    pub g0_um: f64,
    /// Gap now, um (signed: positive while still on the old side).
    pub gap_um: f64,
}

/// Fits G on the grid `d_axis` x `g0_axis` (values row-major: `[id * g0_axis.len() + ig]`).
/// `smooth` weighs second differences along both axes against the data; `anchor[ig]` is imposed
/// (strongly) as G(0, g0_axis[ig]), the gap right after the reversal is registered.
pub fn fit_gap_table(
    samples: &[GapSample],
    d_axis: &[f64],
    g0_axis: &[f64],
    smooth: f64,
    anchor: &[f64],
) -> Option<Vec<f64>> {
    let (nd, ng) = (d_axis.len(), g0_axis.len());
    let n = nd * ng;
    let mut ata = vec![0.0; n * n];
    let mut atb = vec![0.0; n];
    let mut add_row = |idx: &[(usize, f64)], target: f64, w: f64| {
        for &(i, wi) in idx {
            atb[i] += w * wi * target;
            for &(j, wj) in idx {
                ata[i * n + j] += w * wi * wj;
            }
        }
    };
    for s in samples {
        let (id, wd) = cell(d_axis, s.d_mm);
        let (ig, wg) = cell(g0_axis, s.g0_um);
        let idx = [
            (id * ng + ig, (1.0 - wd) * (1.0 - wg)),
            (id * ng + ig + 1, (1.0 - wd) * wg),
            ((id + 1) * ng + ig, wd * (1.0 - wg)),
            ((id + 1) * ng + ig + 1, wd * wg),
        ];
        add_row(&idx, s.gap_um, 1.0);
    }
    // The gap when the reversal is registered, weighted like many samples.
    let weight = 1e3 + samples.len() as f64 / ng as f64;
    for (ig, &g) in anchor.iter().enumerate().take(ng) {
        add_row(&[(ig, 1.0)], g, weight);
    }
    // Second differences in each direction, scaled to the local spacing.
    let w = smooth * (1.0 + samples.len() as f64 / n as f64);
    for id in 0..nd {
        for ig in 1..ng.saturating_sub(1) {
            add_row(
                &[
                    (id * ng + ig - 1, 1.0),
                    (id * ng + ig, -2.0),
                    (id * ng + ig + 1, 1.0),
                ],
                0.0,
                w,
            );
        }
    }
    for ig in 0..ng {
        for id in 1..nd.saturating_sub(1) {
            let (h0, h1) = (d_axis[id] - d_axis[id - 1], d_axis[id + 1] - d_axis[id]);
            let (c0, c2) = (h1 / (h0 + h1), h0 / (h0 + h1));
            add_row(
                &[
                    ((id - 1) * ng + ig, c0),
                    (id * ng + ig, -1.0),
                    ((id + 1) * ng + ig, c2),
                ],
                0.0,
                w,
            );
        }
    }
    // A whisper of ridge keeps cells no sample and no difference reaches well posed.
    for i in 0..n {
        ata[i * n + i] += 1e-9 * (1.0 + samples.len() as f64);
    }
    solve_spd(ata, atb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_equations_recover_a_line_and_its_residual() {
        let mut ne = NormalEquations::new(2);
        // y = 2 x + 1 +- 0.5 at x = 0..3: by hand, the line 1.8 x + 1.3 leaves 0.8.
        for (k, x) in [0.0, 1.0, 2.0, 3.0].into_iter().enumerate() {
            let noise = if k % 2 == 0 { 0.5 } else { -0.5 };
            ne.add(&[x, 1.0], 2.0 * x + 1.0 + noise);
        }
        let (w, sse) = ne.solve(0.0).unwrap();
        assert!(
            (w[0] - 1.8).abs() < 1e-6 && (w[1] - 1.3).abs() < 1e-6,
            "{w:?}"
        );
        assert!((sse - 0.8).abs() < 1e-6, "{sse}");
        assert!(NormalEquations::new(1)
            .solve(0.0)
            .is_some_and(|(w, _)| w[0] == 0.0));
    }

    #[test]
    fn strokes_follow_the_deadband_rule() {
        // up to 100, jitter of 1 (inside a deadband of 2), down to 50, up to 60.
        let mut x: Vec<i32> = (0..=100).collect();
        x.extend([99, 100, 99]);
        x.extend((50..99).rev());
        x.extend(51..=60);
        let s = strokes(&x, 2);
        assert_eq!(s.len(), 3, "{s:?}");
        assert_eq!((s[0].dir, s[1].dir, s[2].dir), (1, -1, 1));
        assert_eq!(s[1].x_turn_counts, 100);
        assert_eq!(s[2].x_turn_counts, 50);
        assert_eq!(s.last().unwrap().end, x.len());
    }

    #[test]
    fn cholesky_solves_small_system() {
        let x = solve_spd(vec![4.0, 2.0, 2.0, 3.0], vec![2.0, 1.0]).unwrap();
        assert!((x[0] - 0.5).abs() < 1e-12 && x[1].abs() < 1e-12);
        assert!(solve_spd(vec![0.0, 0.0, 0.0, 0.0], vec![1.0, 1.0]).is_none());
    }

    #[test]
    fn gap_fit_recovers_a_known_surface() {
        // G(d, g0) = g0 * exp(-d / 10) is linear in g0, smooth in d.
        let d_axis: Vec<f64> = (0..16).map(|i| (i as f64).powi(2) * 0.4).collect();
        let g_axis: Vec<f64> = (0..8).map(|i| i as f64 * 50.0).collect();
        let mut samples = Vec::new();
        for k in 0..40 {
            let g0 = 350.0 * k as f64 / 39.0;
            for i in 0..400 {
                let d = i as f64 * 0.25;
                samples.push(GapSample {
                    d_mm: d,
                    g0_um: g0,
                    gap_um: g0 * (-d / 10.0).exp(),
                });
            }
        }
        let t = fit_gap_table(&samples, &d_axis, &g_axis, 1e-4, &g_axis).unwrap();
        for (id, d) in d_axis.iter().enumerate() {
            for (ig, g0) in g_axis.iter().enumerate() {
                let want = g0 * (-d / 10.0).exp();
                assert!(
                    (t[id * g_axis.len() + ig] - want).abs() < 6.0,
                    "d {d} g0 {g0}: {} vs {want}",
                    t[id * 8 + ig]
                );
            }
        }
    }
}
