//! The 2F-85's register map (Robotiq 2F-85/2F-140 manual, "Control logic" and "Modbus RTU").
//!
//! Six bytes each way, packed high byte first into three 16-bit registers:
//!
//! | register | write (FC 16 at 0x03E8)           | read (FC 3 at 0x07D0)               |
//! |----------|-----------------------------------|-------------------------------------|
//! | 0        | ACTION REQUEST, reserved          | GRIPPER STATUS, reserved            |
//! | 1        | reserved, rPR (position request)  | gFLT (fault), gPR (request echo)    |
//! | 2        | rSP (speed), rFR (force)          | gPO (position), gCU (current/10 mA) |
//!
//! ACTION REQUEST bits: rACT 0 (activate), rGTO 3 (go to rPR), rATR 4 (automatic release),
//! rARD 5 (release direction). GRIPPER STATUS bits: gACT 0, gGTO 3, gSTA 4-5, gOBJ 6-7.
//! Positions are 0 = fully open .. 255 = fully closed, which is DROID's 0 (open) .. 1 (closed).

/// Modbus slave id the 2F-85 answers to (factory setting).
pub const SLAVE_ID: u8 = 0x09;
/// The serial line: 115200 baud, 8 data bits, no parity, 1 stop bit.
pub const BAUD_RATE: u32 = 115_200;
/// First output (robot request) register, written with FC 16.
pub const REQUEST_REGISTER: u16 = 0x03E8;
/// First input (gripper status) register, read with FC 3.
pub const STATUS_REGISTER: u16 = 0x07D0;
/// Registers in each direction.
pub const REGISTERS: u16 = 3;

/// What the robot asks of the gripper (the write registers).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Request {
    /// rACT: 0 resets (and clears major faults), 1 activates.
    pub activate: bool,
    /// rGTO: move to `position` with `speed` and `force`.
    pub go_to: bool,
    /// rATR: automatic release (emergency: open slowly, ignoring the other bits).
    pub auto_release: bool,
    /// rARD: automatic release direction (false = closing, true = opening).
    pub auto_release_open: bool,
    /// rPR: 0 open .. 255 closed.
    pub position: u8,
    /// rSP: 0 slowest .. 255 fastest.
    pub speed: u8,
    /// rFR: 0 lowest grip force (and no re-grasp) .. 255 highest.
    pub force: u8,
}

impl Request {
    /// Reset: everything zero (the first half of the activation sequence).
    pub const RESET: Request = Request {
        activate: false,
        go_to: false,
        auto_release: false,
        auto_release_open: false,
        position: 0,
        speed: 0,
        force: 0,
    };

    /// Activation: rACT set, nothing else.
    pub const ACTIVATE: Request = Request { activate: true, ..Request::RESET };

    /// Move to `position` at `speed` with `force` (rACT + rGTO).
    pub fn go_to(position: u8, speed: u8, force: u8) -> Request {
        Request { activate: true, go_to: true, position, speed, force, ..Request::RESET }
    }

    pub fn action_byte(&self) -> u8 {
        u8::from(self.activate)
            | u8::from(self.go_to) << 3
            | u8::from(self.auto_release) << 4
            | u8::from(self.auto_release_open) << 5
    }

    pub fn to_registers(&self) -> [u16; 3] {
        [
            u16::from(self.action_byte()) << 8,
            u16::from(self.position),
            u16::from(self.speed) << 8 | u16::from(self.force),
        ]
    }

    /// Decodes the three request registers (the emulator's side).
    pub fn from_registers(r: [u16; 3]) -> Request {
        let action = (r[0] >> 8) as u8;
        Request {
            activate: action & 1 != 0,
            go_to: action & (1 << 3) != 0,
            auto_release: action & (1 << 4) != 0,
            auto_release_open: action & (1 << 5) != 0,
            position: (r[1] & 0xFF) as u8,
            speed: (r[2] >> 8) as u8,
            force: (r[2] & 0xFF) as u8,
        }
    }
}

/// gSTA: where the activation stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Activation {
    /// 0: in reset (or automatic release).
    #[default]
    Reset,
    /// 1: activation in progress.
    InProgress,
    /// 2: not used by the 2F-85.
    Unused,
    /// 3: activation complete; the gripper takes motion requests.
    Complete,
}

impl Activation {
    fn from_bits(b: u8) -> Activation {
        match b & 3 {
            0 => Activation::Reset,
            1 => Activation::InProgress,
            2 => Activation::Unused,
            _ => Activation::Complete,
        }
    }

    fn bits(self) -> u8 {
        self as u8
    }
}

/// gOBJ: the object detection status (valid while gGTO = 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Object {
    /// 0: fingers moving toward the requested position, no object yet.
    #[default]
    Moving,
    /// 1: fingers stopped by contact while opening.
    ContactOpening,
    /// 2: fingers stopped by contact while closing: an object is held.
    ContactClosing,
    /// 3: fingers at the requested position, no object detected (or lost).
    AtRequest,
}

impl Object {
    fn from_bits(b: u8) -> Object {
        match b & 3 {
            0 => Object::Moving,
            1 => Object::ContactOpening,
            2 => Object::ContactClosing,
            _ => Object::AtRequest,
        }
    }

    fn bits(self) -> u8 {
        self as u8
    }

    /// An object stopped the fingers.
    pub fn detected(self) -> bool {
        matches!(self, Object::ContactOpening | Object::ContactClosing)
    }
}

/// What the gripper reports (the read registers).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Status {
    /// gACT: echo of rACT.
    pub activated: bool,
    /// gGTO: echo of rGTO.
    pub going: bool,
    /// gSTA.
    pub activation: Activation,
    /// gOBJ.
    pub object: Object,
    /// gFLT (the fault byte's low nibble): 0 = no fault; see [`fault_meaning`].
    pub fault: u8,
    /// kFLT (the fault byte's high nibble): the controller's own fault code, for Robotiq
    /// support; 0 = none.
    pub controller_fault: u8,
    /// gPR: echo of the requested position.
    pub requested: u8,
    /// gPO: the measured position, 0 open .. 255 closed.
    pub position: u8,
    /// gCU: motor current in units of 10 mA.
    pub current: u8,
}

impl Status {
    pub fn status_byte(&self) -> u8 {
        u8::from(self.activated) | u8::from(self.going) << 3 | self.activation.bits() << 4 | self.object.bits() << 6
    }

    pub fn to_registers(&self) -> [u16; 3] {
        [
            u16::from(self.status_byte()) << 8,
            u16::from((self.fault & 0x0F) | self.controller_fault << 4) << 8 | u16::from(self.requested),
            u16::from(self.position) << 8 | u16::from(self.current),
        ]
    }

    pub fn from_registers(r: [u16; 3]) -> Status {
        let s = (r[0] >> 8) as u8;
        Status {
            activated: s & 1 != 0,
            going: s & (1 << 3) != 0,
            activation: Activation::from_bits(s >> 4),
            object: Object::from_bits(s >> 6),
            fault: ((r[1] >> 8) & 0x0F) as u8,
            controller_fault: (r[1] >> 12) as u8,
            requested: (r[1] & 0xFF) as u8,
            position: (r[2] >> 8) as u8,
            current: (r[2] & 0xFF) as u8,
        }
    }

    /// Ready for motion requests: activated and no fault that blocks motion.
    pub fn ready(&self) -> bool {
        self.activation == Activation::Complete && !fault_blocks_motion(self.fault)
    }

    /// The motor current in mA.
    pub fn current_ma(&self) -> f64 {
        f64::from(self.current) * 10.0
    }

    /// A one-line summary for logs and errors.
    pub fn describe(&self) -> String {
        format!(
            "gACT={} gGTO={} gSTA={:?} gOBJ={:?} gFLT=0x{:02X} gPR={} gPO={} gCU={}",
            u8::from(self.activated),
            u8::from(self.going),
            self.activation,
            self.object,
            self.fault,
            self.requested,
            self.position,
            self.current
        )
    }
}

/// What a gFLT code means, from the manual's fault table; `None` for codes it does not list.
pub fn fault_meaning(code: u8) -> Option<&'static str> {
    Some(match code {
        0x00 => "no fault",
        0x05 => "action delayed: the (re)activation must complete before the action",
        0x07 => "the activation bit must be set before an action",
        0x08 => "maximum operating temperature exceeded (>= 85 C): wait for it to cool down",
        0x09 => "no communication for at least 1 second",
        0x0A => "under minimum operating voltage",
        0x0B => "automatic release in progress",
        0x0C => "internal fault: contact Robotiq support",
        0x0D => "activation fault: check that nothing blocks the fingers",
        0x0E => "overcurrent triggered",
        0x0F => "automatic release completed",
        _ => return None,
    })
}

/// Major faults (0x0A and up) stop the gripper until it is reset (rACT 0 -> 1); minor ones
/// (0x08, 0x09) and the priority faults (0x05, 0x07) clear themselves.
pub fn fault_is_major(code: u8) -> bool {
    code >= 0x0A
}

/// Faults the gripper does not move under: the major ones and the over-temperature stop.
pub fn fault_blocks_motion(code: u8) -> bool {
    fault_is_major(code) || code == 0x08
}

/// DROID's gripper action (0 open .. 1 closed) as rPR. NaN and values outside 0..1 are the
/// caller's to refuse; this clamps.
pub fn droid_to_counts(x: f64) -> u8 {
    (x.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// A register value (gPO, gPR) as DROID's 0 open .. 1 closed.
pub fn counts_to_droid(c: u8) -> f64 {
    f64::from(c) / 255.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_pack_like_the_manuals_examples() {
        // Manual, "Modbus RTU example": activation request 09 10 03E8 0003 06 0100 0000 0000.
        assert_eq!(Request::ACTIVATE.to_registers(), [0x0100, 0x0000, 0x0000]);
        // Close at full speed and force: 09 10 03E8 0003 06 0900 00FF FFFF.
        assert_eq!(Request::go_to(255, 255, 255).to_registers(), [0x0900, 0x00FF, 0xFFFF]);
        let r = Request { auto_release: true, auto_release_open: true, ..Request::go_to(12, 34, 56) };
        assert_eq!(Request::from_registers(r.to_registers()), r);
    }

    #[test]
    fn status_round_trips_and_decodes_the_manuals_reply() {
        // Manual: after activation + a close on an object, status 0xB9 = gACT, gGTO, gSTA 3, gOBJ 2.
        let s = Status::from_registers([0xB900, 0x00FF, 0xBD00]);
        assert!(s.activated && s.going);
        assert_eq!(s.activation, Activation::Complete);
        assert_eq!(s.object, Object::ContactClosing);
        assert!(s.object.detected());
        assert_eq!((s.fault, s.requested, s.position, s.current), (0, 255, 0xBD, 0));
        assert_eq!(Status::from_registers(s.to_registers()), s);
        // The fault byte: gFLT in the low nibble, kFLT (controller) in the high one.
        let f = Status::from_registers([0x3100, 0x5E00, 0x0000]);
        assert_eq!((f.fault, f.controller_fault), (0x0E, 0x05));
        assert_eq!(Status::from_registers(f.to_registers()), f);
        assert_eq!(fault_meaning(0x0E), Some("overcurrent triggered"));
        assert_eq!(fault_meaning(0x01), None);
        assert!(fault_is_major(0x0D) && !fault_is_major(0x09));
    }

    #[test]
    fn droid_scale() {
        assert_eq!(droid_to_counts(0.0), 0);
        assert_eq!(droid_to_counts(1.0), 255);
        assert_eq!(droid_to_counts(0.5), 128);
        assert!((counts_to_droid(255) - 1.0).abs() < 1e-12);
    }
}
