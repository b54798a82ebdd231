//! TEMPORARY stand-in for estimator_core::drive until the lead declares it. REMOVE.
#![allow(missing_docs, dead_code)]
use estimator_core::fixed::types::I16F16;
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Sample { pub motor_counter: u16, pub scale_counter: u16 }
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Faults(pub u8);
impl Faults { pub fn is_clear(self) -> bool { self.0 == 0 } }
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Telemetry { pub tick: u32, pub motor_counts: i32, pub scale_counts: i32, pub setpoint_counts: i32, pub following_error_counts: i32, pub est_error_um: I16F16, pub current_a: I16F16, pub faults: Faults, pub model: ModelKind, pub moving: bool }
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Output { pub current_a: I16F16, pub telemetry: Telemetry }
pub use estimator_core::model::ModelKind;
pub use estimator_core::ConfigError;
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Command { MoveTo { target_um: i32, velocity_um_s: u32, accel_um_s2: u32 }, Stop, Enable, Disable, ClearFaults, SelectModel(ModelKind), Home { position_um: i32, scale_um: i32 } }
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CommandError { TargetOutOfTravel, VelocityOutOfRange, AccelOutOfRange, NotEnabled, ModelNotCalibrated, Busy }
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlobError { Length, Crc }
pub struct DriveConfig { pub control_rate_hz: u32 }
impl DriveConfig { pub fn paper_rig() -> Self { DriveConfig { control_rate_hz: 2000 } } }
pub struct Drive { t: Telemetry }
impl Drive {
    pub fn new(_c: &DriveConfig) -> Result<Drive, ConfigError> { Ok(Drive { t: Telemetry::default() }) }
    pub fn command(&mut self, _c: Command) -> Result<(), CommandError> { Ok(()) }
    pub fn step(&mut self, s: Sample) -> Output { self.t.tick += 1; self.t.motor_counts = s.motor_counter as i32; Output { current_a: I16F16::ZERO, telemetry: self.t } }
    pub fn load_calibration(&mut self, _b: &[u8]) -> Result<(), BlobError> { Ok(()) }
}
pub mod blob { pub const MAX_BYTES: usize = 2048; }

impl BlobError { pub fn as_str(self) -> &'static str { "x" } }
