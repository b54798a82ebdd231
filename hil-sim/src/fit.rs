//! A small Nelder-Mead simplex minimiser for the least-squares fits of Models 1 and 2.
//!
//! The models are piecewise (reversal logic, max/min against the band edges), so their residuals
//! have no useful derivatives; a derivative-free simplex on the sum of squares is robust here and
//! needs only a few hundred evaluations for 6-8 parameters.

/// Result of a minimisation.
#[derive(Clone, Debug)]
pub struct Minimum {
    /// Best point found.
    pub x: Vec<f64>,
    /// Objective at `x`.
    pub value: f64,
    /// Objective evaluations spent.
    pub evaluations: usize,
}

/// Minimises `f` from `x0` with initial steps `step` (one per coordinate), until the simplex's
/// spread of values falls below `tol` (relative) or `max_evals` is reached.
pub fn nelder_mead(
    mut f: impl FnMut(&[f64]) -> f64,
    x0: &[f64],
    step: &[f64],
    tol: f64,
    max_evals: usize,
) -> Minimum {
    let n = x0.len();
    assert_eq!(step.len(), n, "one initial step per coordinate");
    let mut evals = 0usize;
    let mut eval = |x: &[f64], evals: &mut usize| {
        *evals += 1;
        let v = f(x);
        if v.is_finite() {
            v
        } else {
            f64::INFINITY
        }
    };
    let mut pts: Vec<Vec<f64>> = vec![x0.to_vec()];
    for i in 0..n {
        let mut p = x0.to_vec();
        p[i] += step[i];
        pts.push(p);
    }
    let mut vals: Vec<f64> = pts.iter().map(|p| eval(p, &mut evals)).collect();
    let (alpha, gamma, rho, sigma) = (1.0, 2.0, 0.5, 0.5);
    while evals < max_evals {
        let mut order: Vec<usize> = (0..=n).collect();
        order.sort_by(|&a, &b| vals[a].total_cmp(&vals[b]));
        pts = order.iter().map(|&i| pts[i].clone()).collect();
        vals = order.iter().map(|&i| vals[i]).collect();
        let spread = (vals[n] - vals[0]).abs();
        if spread <= tol * (vals[0].abs() + 1e-30) {
            break;
        }
        let centroid: Vec<f64> = (0..n)
            .map(|j| pts[..n].iter().map(|p| p[j]).sum::<f64>() / n as f64)
            .collect();
        let towards = |t: f64, p: &[f64]| -> Vec<f64> {
            (0..n)
                .map(|j| centroid[j] + t * (p[j] - centroid[j]))
                .collect()
        };
        let xr = towards(-alpha, &pts[n]);
        let fr = eval(&xr, &mut evals);
        if fr < vals[0] {
            let xe = towards(-gamma, &pts[n]);
            let fe = eval(&xe, &mut evals);
            if fe < fr {
                pts[n] = xe;
                vals[n] = fe;
            } else {
                pts[n] = xr;
                vals[n] = fr;
            }
        } else if fr < vals[n - 1] {
            pts[n] = xr;
            vals[n] = fr;
        } else {
            let (xc, fc) = if fr < vals[n] {
                let xc = towards(-rho, &pts[n]);
                let fc = eval(&xc, &mut evals);
                (xc, fc)
            } else {
                let xc = towards(rho, &pts[n]);
                let fc = eval(&xc, &mut evals);
                (xc, fc)
            };
            if fc < vals[n].min(fr) {
                pts[n] = xc;
                vals[n] = fc;
            } else {
                for i in 1..=n {
                    pts[i] = (0..n)
                        .map(|j| pts[0][j] + sigma * (pts[i][j] - pts[0][j]))
                        .collect();
                    vals[i] = eval(&pts[i], &mut evals);
                }
            }
        }
    }
    let best = (0..=n)
        .min_by(|&a, &b| vals[a].total_cmp(&vals[b]))
        .unwrap_or(0);
    Minimum {
        x: pts[best].clone(),
        value: vals[best],
        evaluations: evals,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_rosenbrock_minimum() {
        let m = nelder_mead(
            |x| (1.0 - x[0]).powi(2) + 100.0 * (x[1] - x[0] * x[0]).powi(2),
            &[-1.2, 1.0],
            &[0.5, 0.5],
            1e-14,
            5000,
        );
        assert!(
            (m.x[0] - 1.0).abs() < 1e-3 && (m.x[1] - 1.0).abs() < 1e-3,
            "{:?}",
            m
        );
    }

    #[test]
    fn recovers_line_parameters_by_least_squares() {
        let xs: Vec<f64> = (0..50).map(|i| i as f64).collect();
        let m = nelder_mead(
            |p| {
                xs.iter()
                    .map(|x| (p[0] * x + p[1] - (0.3 * x - 2.0)).powi(2))
                    .sum()
            },
            &[0.0, 0.0],
            &[0.1, 1.0],
            1e-16,
            4000,
        );
        assert!(
            (m.x[0] - 0.3).abs() < 1e-4 && (m.x[1] + 2.0).abs() < 1e-3,
            "{:?}",
            m
        );
    }
}
