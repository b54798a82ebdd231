//! What a host asks of the drive: one [`Command`] type, the same on the wire and in the drive,
//! its refusals ([`CommandError`]) and the compensator numbers ([`ModelKind`]).

/// Which compensator the drive's estimate uses (the drive's `model::estimate` evaluates it).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
#[repr(u8)]
pub enum ModelKind {
    /// No compensation: the estimate is 0.
    #[default]
    None = 0,
    /// Model 1: linear transition (eq. 14).
    Linear = 1,
    /// Model 2: exponential transition (eq. 17).
    Exponential = 2,
    /// Model 3: lookup tables (eq. 18).
    Table = 3,
    /// Baseline: constant backlash by direction (LinuxCNC `BACKLASH`, Marlin `M425`).
    Backlash = 4,
    /// Baseline: bidirectional position table (LinuxCNC `COMP_FILE`).
    BidirTable = 5,
    /// Model 4: play operators, band shape, tooth harmonic and current (the project's own).
    Operator = 6,
}

impl ModelKind {
    /// Every kind, in numeric order.
    pub const ALL: [ModelKind; 7] = [
        ModelKind::None,
        ModelKind::Linear,
        ModelKind::Exponential,
        ModelKind::Table,
        ModelKind::Backlash,
        ModelKind::BidirTable,
        ModelKind::Operator,
    ];

    /// The paper's three models.
    pub const PAPER_MODELS: [ModelKind; 3] =
        [ModelKind::Linear, ModelKind::Exponential, ModelKind::Table];

    /// The kind with this number (`0..=6`), e.g. from a command byte.
    pub const fn from_u8(v: u8) -> Option<ModelKind> {
        match v {
            0 => Some(ModelKind::None),
            1 => Some(ModelKind::Linear),
            2 => Some(ModelKind::Exponential),
            3 => Some(ModelKind::Table),
            4 => Some(ModelKind::Backlash),
            5 => Some(ModelKind::BidirTable),
            6 => Some(ModelKind::Operator),
            _ => None,
        }
    }

    /// `"none"`, `"model1"`, `"model2"`, `"model3"`, `"backlash"`, `"bidir_table"` or `"model4"`.
    pub const fn as_str(self) -> &'static str {
        match self {
            ModelKind::None => "none",
            ModelKind::Linear => "model1",
            ModelKind::Exponential => "model2",
            ModelKind::Table => "model3",
            ModelKind::Backlash => "backlash",
            ModelKind::BidirTable => "bidir_table",
            ModelKind::Operator => "model4",
        }
    }

    /// The inverse of [`ModelKind::as_str`].
    pub fn parse(s: &str) -> Option<ModelKind> {
        ModelKind::ALL.into_iter().find(|k| k.as_str() == s)
    }
}

/// A name that is no [`ModelKind`]; displays the names there are (for command lines and files).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UnknownModel;

impl core::fmt::Display for UnknownModel {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("use one of")?;
        for (i, k) in ModelKind::ALL.iter().enumerate() {
            f.write_str(if i == 0 { " " } else { ", " })?;
            f.write_str(k.as_str())?;
        }
        Ok(())
    }
}

impl core::error::Error for UnknownModel {}

impl core::str::FromStr for ModelKind {
    type Err = UnknownModel;

    fn from_str(s: &str) -> Result<ModelKind, UnknownModel> {
        ModelKind::parse(s).ok_or(UnknownModel)
    }
}

impl core::fmt::Display for ModelKind {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Commands from the link, in integer SI units so that no float crosses the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Command {
    /// Move the motor to `target_um` of nominal carriage travel, no compensation: calibration
    /// needs raw motor trajectories.
    MoveMotorTo {
        /// Target, micrometres of nominal travel from the encoder's zero.
        target_um: i32,
        /// Cruise speed, micrometres per second (> 0).
        velocity_um_s: u32,
        /// Acceleration and deceleration, micrometres per second squared (> 0).
        accel_um_s2: u32,
    },
    /// Move the carriage to `target_um` of carriage travel (as the linear scale would read it):
    /// the motor's target is the active model's inverse along the planned path, so the carriage,
    /// not the motor, arrives there. With no compensator active it is a motor move.
    MoveTo {
        /// Carriage target, micrometres of travel from the home position.
        target_um: i32,
        /// Cruise speed of the motor, micrometres per second (> 0).
        velocity_um_s: u32,
        /// Acceleration and deceleration of the motor, micrometres per second squared (> 0).
        accel_um_s2: u32,
    },
    /// Decelerate to rest at the configured acceleration.
    Stop,
    /// Enable the current output (the drive starts disabled).
    Enable,
    /// Zero current at once and stay so.
    Disable,
    /// Clear latched faults (the drive stays disabled until `Enable`).
    ClearFaults,
    /// Select the error model used for the estimate.
    SelectModel(ModelKind),
    /// Run the homing routine of the configuration (`homing.*`): at low speed and reduced
    /// current towards a hard stop; the stop becomes `homing.position_mm`, the estimator starts
    /// on the band edge of the approach direction, and the drive backs off. Needs the drive
    /// enabled and at rest.
    Homing,
    /// Homing by declaration: the motor now stands at `position_um` of nominal travel (motor
    /// encoder) and the linear scale, if fitted, reads `scale_um`. Refused while moving.
    Home {
        /// Motor position to assign, micrometres of nominal travel.
        position_um: i32,
        /// Linear-scale position to assign, micrometres.
        scale_um: i32,
    },
}

impl Command {
    /// A move to `target_um`: of carriage travel ([`Command::MoveTo`]) when `carriage`, else of
    /// nominal motor travel ([`Command::MoveMotorTo`]).
    pub const fn move_to(
        carriage: bool,
        target_um: i32,
        velocity_um_s: u32,
        accel_um_s2: u32,
    ) -> Command {
        if carriage {
            Command::MoveTo {
                target_um,
                velocity_um_s,
                accel_um_s2,
            }
        } else {
            Command::MoveMotorTo {
                target_um,
                velocity_um_s,
                accel_um_s2,
            }
        }
    }
}

/// Why a command was refused; refused commands change nothing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CommandError {
    /// Target outside the configured travel.
    TargetOutOfTravel,
    /// Velocity zero or above the configured maximum.
    VelocityOutOfRange,
    /// Acceleration zero or above the configured maximum.
    AccelOutOfRange,
    /// The drive is faulted or disabled.
    NotEnabled,
    /// The command needs the drive at rest.
    Busy,
    /// Moves are refused until the drive is homed.
    NotHomed,
    /// No valid configuration: set one (`ConfigSet`, `ConfigApply`) or store one.
    Unconfigured,
    /// The selected model needs a calibration for this drive's geometry: load one first.
    NotCalibrated,
    /// The applied configuration has another control rate than the tick runs at (it is set at
    /// boot): enabling is refused until the drive restarts with it stored.
    RestartNeeded,
}

impl core::fmt::Display for CommandError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            CommandError::TargetOutOfTravel => "target outside the configured travel",
            CommandError::VelocityOutOfRange => "velocity zero or above the configured maximum",
            CommandError::AccelOutOfRange => "acceleration zero or above the configured maximum",
            CommandError::NotEnabled => "drive disabled or faulted",
            CommandError::Busy => "the drive must be at rest",
            CommandError::NotHomed => "not homed: home the drive before moving",
            CommandError::Unconfigured => {
                "the drive is not configured: set and apply a configuration"
            }
            CommandError::NotCalibrated => "no calibration for this geometry: load one first",
            CommandError::RestartNeeded => {
                "the control rate changed: save the configuration and restart the drive"
            }
        })
    }
}

impl CommandError {
    /// Every refusal.
    pub const ALL: [CommandError; 9] = [
        CommandError::TargetOutOfTravel,
        CommandError::VelocityOutOfRange,
        CommandError::AccelOutOfRange,
        CommandError::NotEnabled,
        CommandError::Busy,
        CommandError::NotHomed,
        CommandError::Unconfigured,
        CommandError::NotCalibrated,
        CommandError::RestartNeeded,
    ];

    /// Wire code (`detail` of [`crate::LinkError::Refused`]).
    pub const fn code(self) -> u8 {
        match self {
            CommandError::TargetOutOfTravel => 1,
            CommandError::VelocityOutOfRange => 2,
            CommandError::AccelOutOfRange => 3,
            CommandError::NotEnabled => 4,
            CommandError::Busy => 6,
            CommandError::NotHomed => 7,
            CommandError::Unconfigured => 8,
            CommandError::NotCalibrated => 9,
            CommandError::RestartNeeded => 10,
        }
    }

    /// The refusal with wire code `code`.
    pub const fn from_code(code: u8) -> Option<CommandError> {
        Some(match code {
            1 => CommandError::TargetOutOfTravel,
            2 => CommandError::VelocityOutOfRange,
            3 => CommandError::AccelOutOfRange,
            4 => CommandError::NotEnabled,
            6 => CommandError::Busy,
            7 => CommandError::NotHomed,
            8 => CommandError::Unconfigured,
            9 => CommandError::NotCalibrated,
            10 => CommandError::RestartNeeded,
            _ => return None,
        })
    }
}
