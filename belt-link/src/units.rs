//! Positions in their own types: motor encoder counts and linear-scale counts are both `i32`
//! on the wire and in the per-tick arithmetic, but they are different lengths (one motor count
//! is 0.535 um of belt on the paper rig, one scale count 0.5 um of carriage), and mixing them
//! is a silent error of 7 %. Where positions leave the drive (its telemetry, and every wire type
//! here) they carry their unit in the type; `.0` is the raw count where arithmetic needs it.

/// Motor encoder counts (x4 quadrature of the motor's encoder), the drive's position unit.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[repr(transparent)]
pub struct MotorCounts(pub i32);

/// Linear-scale counts (x4 quadrature of a 500 lines/mm scale: 0.5 um each).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[repr(transparent)]
pub struct ScaleCounts(pub i32);

impl MotorCounts {
    /// Millimetres of nominal travel at `counts_per_mm` (host tools, plots).
    pub fn to_mm(self, counts_per_mm: f64) -> f64 {
        self.0 as f64 / counts_per_mm
    }
}

/// The raw count (CSV columns, messages).
impl core::fmt::Display for MotorCounts {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        self.0.fmt(f)
    }
}

/// The raw count (CSV columns, messages).
impl core::fmt::Display for ScaleCounts {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        self.0.fmt(f)
    }
}
