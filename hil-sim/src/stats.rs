//! Table 3's statistics of e = x_LS - x_PE - y (eq. 19), in micrometres.

use serde::Serialize;

/// Max, min and RMS of an error sequence, um.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ErrorStats {
    /// Largest error, um.
    pub max_um: f64,
    /// Smallest error, um.
    pub min_um: f64,
    /// Root mean square (eq. 19), um.
    pub rms_um: f64,
}

impl ErrorStats {
    /// Statistics of `e`; `None` for an empty sequence.
    pub fn of(e: impl IntoIterator<Item = f64>) -> Option<ErrorStats> {
        let (mut max, mut min, mut ss, mut n) = (f64::NEG_INFINITY, f64::INFINITY, 0.0, 0usize);
        for v in e {
            max = max.max(v);
            min = min.min(v);
            ss += v * v;
            n += 1;
        }
        (n > 0).then(|| ErrorStats {
            max_um: max,
            min_um: min,
            rms_um: (ss / n as f64).sqrt(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_of_known_sequence() {
        let s = ErrorStats::of([3.0, -4.0]).unwrap();
        assert_eq!((s.max_um, s.min_um), (3.0, -4.0));
        assert!((s.rms_um - (12.5f64).sqrt()).abs() < 1e-12);
        assert!(ErrorStats::of([]).is_none());
    }
}
