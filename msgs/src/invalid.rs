//! The one validation error of the workspace: a value that breaks a rule, named by its key.

/// A value that breaks a rule: a config key (`safety.period_s`, `ros.domain_id`) or a message
/// field (`mode`, `version`), and what is wrong with it. Message and config checks in every
/// crate return this, so a node's start-up error and a decoder's error read the same way.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{message}")]
pub struct Invalid {
    /// Where the value is: a dotted config key or a message field.
    pub key: String,
    /// What is wrong, as a whole sentence that names the key (it is what is printed).
    pub message: String,
}

impl Invalid {
    pub fn new(key: impl Into<String>, message: impl Into<String>) -> Invalid {
        Invalid { key: key.into(), message: message.into() }
    }
}
