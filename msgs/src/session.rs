//! The operator's session (serde): who is collecting, where, and the task, as the operator
//! station (`labrig station`) sets it and publishes it, latched, on [`crate::topics::RIG_SESSION`]
//! (JSON in a `std_msgs/String`). The loop takes `lab` and `operator` into each episode's uuid
//! (DROID's `<lab>+<user>+<time>`), the recorder writes every field into the episode's metadata
//! (`user`, `lab`, `building`, `scene_id`, and `task` as the instruction when the Start names
//! none). An empty field leaves the node's own setting.

use crate::Invalid;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Session {
    pub operator: String,
    pub lab: String,
    pub building: String,
    /// DROID asks at each start "has the scene changed?": the operator's id for the scene.
    pub scene_id: String,
    /// The task instruction.
    pub task: String,
}

/// The longest a field may be (bytes).
pub const MAX_FIELD: usize = 200;

impl Session {
    /// Each field at most [`MAX_FIELD`] bytes, without control characters; `lab` and
    /// `operator` (parts of the uuid, which names folders) without `+`, `/` or whitespace.
    pub fn validate(&self) -> Result<(), Invalid> {
        for (name, v) in [
            ("operator", &self.operator),
            ("lab", &self.lab),
            ("building", &self.building),
            ("scene_id", &self.scene_id),
            ("task", &self.task),
        ] {
            if v.len() > MAX_FIELD {
                return Err(Invalid::new(name, format!("{name} is {} bytes, at most {MAX_FIELD}", v.len())));
            }
            if v.chars().any(char::is_control) {
                return Err(Invalid::new(name, format!("{name} holds a control character")));
            }
        }
        for (name, v) in [("operator", &self.operator), ("lab", &self.lab)] {
            if v.chars().any(|c| c == '+' || c == '/' || c == '\\' || c.is_whitespace()) {
                return Err(Invalid::new(
                    name,
                    format!("{name} `{v}` is part of the episode's uuid: no '+', '/', '\\' or spaces"),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uuid_parts_and_sizes_are_checked_by_name() {
        let ok = Session {
            operator: "alice".into(),
            lab: "AUTOLab".into(),
            task: "put the cube in the bin".into(),
            ..Default::default()
        };
        assert!(ok.validate().is_ok());
        let e = Session { operator: "alice smith".into(), ..ok.clone() }.validate().unwrap_err();
        assert!(e.to_string().contains("operator `alice smith` is part of the episode's uuid"), "{e}");
        let e = Session { task: "x".repeat(201), ..ok.clone() }.validate().unwrap_err();
        assert!(e.to_string().contains("task is 201 bytes"), "{e}");
        let e = Session { building: "a\nb".into(), ..ok }.validate().unwrap_err();
        assert!(e.to_string().contains("building holds a control character"), "{e}");
    }
}
