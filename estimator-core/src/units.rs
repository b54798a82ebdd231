//! Positions in their own types, defined with the wire types that carry them
//! ([`belt_link::units`]).

pub use belt_link::units::{MotorCounts, ScaleCounts};
