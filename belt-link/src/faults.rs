//! The fault bits the drive latches and reports: numbers on the wire, names in logs, status
//! replies and the host tools. What raises each bit is the drive's (`estimator-core`'s `fault`
//! module); the vocabulary is the protocol's, so both ends name a fault the same way.

/// Latched fault bits: any set bit forces zero current and a low amplifier enable until
/// `Command::ClearFaults` and `Command::Enable`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Faults(pub u16);

impl Faults {
    /// The encoder moved more in one tick than the plausibility limit allows (count glitch,
    /// noise on an unplugged cable).
    pub const ENCODER_JUMP: u16 = 1 << 0;
    /// The following error exceeded its speed-dependent limit.
    pub const FOLLOWING_ERROR: u16 = 1 << 1;
    /// The motor position left the configured travel (plus margin).
    pub const TRAVEL_LIMIT: u16 = 1 << 2;
    /// The link to the host went silent.
    pub const LINK_TIMEOUT: u16 = 1 << 3;
    /// Current above the stall threshold with no encoder motion: a jammed carriage, a stalled
    /// motor, or a lost encoder (line cut, counter stuck).
    pub const STALL: u16 = 1 << 4;
    /// Sustained acceleration against the sign of the current: motor wires or encoder reversed,
    /// or an external force driving the axis.
    pub const RUNAWAY: u16 = 1 << 5;
    /// The motor ran faster than the configured maximum velocity by more than a margin.
    pub const OVERSPEED: u16 = 1 << 6;
    /// The current command sat at the drive's limit for too long (move beyond the amplifier).
    pub const CURRENT_SATURATION: u16 = 1 << 7;
    /// A control tick ran late or was missed (reported by the board or the runner).
    pub const DEADLINE_MISSED: u16 = 1 << 8;
    /// The clock security system saw the crystal fail (board only).
    pub const CLOCK_FAILURE: u16 = 1 << 9;
    /// The homing routine searched the whole travel without finding its stop.
    pub const HOMING_FAILED: u16 = 1 << 10;
    /// No fault.
    pub const NONE: Faults = Faults(0);
    /// Every defined bit.
    pub const ALL: u16 = (1 << 11) - 1;

    /// Every bit with its name, in bit order. The names are what logs, status replies and
    /// `hil-sim` print.
    pub const NAMES: [(u16, &'static str); 11] = [
        (Self::ENCODER_JUMP, "encoder_jump"),
        (Self::FOLLOWING_ERROR, "following_error"),
        (Self::TRAVEL_LIMIT, "travel_limit"),
        (Self::LINK_TIMEOUT, "link_timeout"),
        (Self::STALL, "stall"),
        (Self::RUNAWAY, "runaway"),
        (Self::OVERSPEED, "overspeed"),
        (Self::CURRENT_SATURATION, "current_saturation"),
        (Self::DEADLINE_MISSED, "deadline_missed"),
        (Self::CLOCK_FAILURE, "clock_failure"),
        (Self::HOMING_FAILED, "homing_failed"),
    ];

    /// True when no fault bit is set.
    pub fn is_clear(self) -> bool {
        self.0 == 0
    }

    /// True when `bit` is set.
    pub fn has(self, bit: u16) -> bool {
        self.0 & bit != 0
    }

    /// The name of a single fault bit (`"unknown"` for anything else).
    pub fn name(bit: u16) -> &'static str {
        match Self::NAMES.iter().find(|(b, _)| *b == bit) {
            Some((_, n)) => n,
            None => "unknown",
        }
    }

    /// The bit of a fault name, if it is one.
    pub fn from_name(name: &str) -> Option<u16> {
        Self::NAMES
            .iter()
            .find(|(_, n)| *n == name)
            .map(|(b, _)| *b)
    }

    /// The names of the set bits, in bit order.
    pub fn names(self) -> impl Iterator<Item = &'static str> {
        Self::NAMES
            .into_iter()
            .filter(move |(b, _)| self.0 & b != 0)
            .map(|(_, n)| n)
    }
}

impl core::fmt::Display for Faults {
    /// `none`, or the names joined by `+` (`stall+following_error`); unknown bits as hex.
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        if self.0 == 0 {
            return f.write_str("none");
        }
        let mut first = true;
        for n in self.names() {
            if !first {
                f.write_str("+")?;
            }
            f.write_str(n)?;
            first = false;
        }
        let unknown = self.0 & !Self::ALL;
        if unknown != 0 {
            if !first {
                f.write_str("+")?;
            }
            write!(f, "unknown(0x{unknown:04x})")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_display() {
        for (bit, name) in Faults::NAMES {
            assert_eq!(Faults::name(bit), name);
            assert_eq!(Faults::from_name(name), Some(bit));
        }
        assert_eq!(Faults::name(0), "unknown");
        assert_eq!(Faults::name(Faults::STALL | Faults::RUNAWAY), "unknown");
        let f = Faults(Faults::STALL | Faults::FOLLOWING_ERROR);
        assert_eq!(format!("{f}"), "following_error+stall");
        assert_eq!(format!("{}", Faults::NONE), "none");
        assert_eq!(format!("{}", Faults(1 << 15)), "unknown(0x8000)");
        // Every bit has exactly one name.
        let mut all = 0;
        for (bit, _) in Faults::NAMES {
            assert_eq!(bit.count_ones(), 1);
            assert_eq!(all & bit, 0);
            all |= bit;
        }
        assert_eq!(all, Faults::ALL);
    }
}
