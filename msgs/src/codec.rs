//! The one CDR entry point: [`encode`] and [`decode`] for every [`RosMessage`].
//!
//! Wire layout (what Fast DDS puts on the wire for ROS 2, and rosbag2 records): a 4-byte
//! encapsulation header (representation id as a big-endian u16, then a u16 options field that
//! ROS 2 leaves 0), the CDR body, then 0-3 zero bytes padding the body to a multiple of 4.
//! rclpy's `serialize_message` returns the same body without the final padding (and with
//! uninitialised alignment bytes); both forms decode.

use crate::RosMessage;
use cdr_encoding::{from_bytes, to_vec};

/// Representation identifier of plain CDR, little endian (what ROS 2 writes on x86/ARM).
pub const CDR_LE: [u8; 2] = [0x00, 0x01];
/// Representation identifier of plain CDR, big endian.
pub const CDR_BE: [u8; 2] = [0x00, 0x00];

use byteorder::{BigEndian as BE, LittleEndian as LE};

/// Why a buffer could not be encoded or decoded. Every variant names the message type.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    #[error("{type_name}: buffer of {len} bytes is shorter than the 4-byte CDR encapsulation header")]
    MissingHeader { type_name: &'static str, len: usize },
    #[error("{type_name}: unsupported encapsulation {id:02x?} (expected CDR little endian 00 01 or big endian 00 00)")]
    UnsupportedEncapsulation { type_name: &'static str, id: [u8; 2] },
    #[error("{type_name}: malformed or truncated CDR body: {source}")]
    Malformed {
        type_name: &'static str,
        #[source]
        source: cdr_encoding::Error,
    },
    #[error("{type_name}: {extra} unexpected bytes after the end of the message (body is {body} bytes)")]
    TrailingBytes { type_name: &'static str, extra: usize, body: usize },
    #[error("{type_name}: invalid value: {reason}")]
    Invalid {
        type_name: &'static str,
        #[source]
        reason: crate::Invalid,
    },
    #[error("{type_name}: cannot encode: {source}")]
    Encode {
        type_name: &'static str,
        #[source]
        source: cdr_encoding::Error,
    },
}

/// Encodes `msg` exactly as ROS 2 puts it on the wire: header, little-endian CDR body, zero
/// padding to a multiple of 4.
pub fn encode<T: RosMessage>(msg: &T) -> Result<Vec<u8>, CodecError> {
    let body = to_vec::<T, LE>(msg).map_err(|source| CodecError::Encode { type_name: T::TYPE_NAME, source })?;
    let padding = (4 - body.len() % 4) % 4;
    let mut out = Vec::with_capacity(4 + body.len() + padding);
    out.extend_from_slice(&CDR_LE);
    out.extend_from_slice(&[0x00, 0x00]);
    out.extend_from_slice(&body);
    out.resize(out.len() + padding, 0);
    Ok(out)
}

/// Decodes a buffer with its encapsulation header (what an MCAP `cdr` message or a DDS sample
/// holds). Trailing bytes beyond the declared alignment padding are an error. rclpy's
/// `serialize_message` can return more: its buffer is sized by rmw's estimate (4 bytes past the
/// data for a JointState with an empty `effort`) and the excess is not zeroed; cut such a
/// buffer at its data first (tests/tests/cdr_rclpy.rs shows how its written bytes are found).
pub fn decode<T: RosMessage>(bytes: &[u8]) -> Result<T, CodecError> {
    let type_name = T::TYPE_NAME;
    if bytes.len() < 4 {
        return Err(CodecError::MissingHeader { type_name, len: bytes.len() });
    }
    let id = [bytes[0], bytes[1]];
    let declared_padding = (bytes[3] & 0b11) as usize;
    decode_body::<T>(id, &bytes[4..], Some(declared_padding))
}

/// Decodes a CDR body without the encapsulation header, given its representation id (what a DDS
/// reader hands over after stripping the header). Up to 3 zero padding bytes may follow.
pub fn decode_payload<T: RosMessage>(id: [u8; 2], body: &[u8]) -> Result<T, CodecError> {
    decode_body::<T>(id, body, None)
}

/// The CDR body in either byte order (`id` checked by the caller), with the bytes it used.
pub(crate) fn from_cdr<T: serde::de::DeserializeOwned>(
    id: [u8; 2],
    body: &[u8],
) -> Result<(T, usize), cdr_encoding::Error> {
    if id == CDR_BE { from_bytes::<T, BE>(body) } else { from_bytes::<T, LE>(body) }
}

fn decode_body<T: RosMessage>(id: [u8; 2], body: &[u8], declared_padding: Option<usize>) -> Result<T, CodecError> {
    let type_name = T::TYPE_NAME;
    if id != CDR_LE && id != CDR_BE {
        return Err(CodecError::UnsupportedEncapsulation { type_name, id });
    }
    let (msg, used) = match from_cdr::<T>(id, body) {
        Ok(m) => m,
        // A body too short for the current layout may be the type's earlier one.
        Err(source) => match T::decode_legacy(id, body) {
            Some(Ok(m)) => m,
            _ => return Err(CodecError::Malformed { type_name, source }),
        },
    };
    let rest = &body[used.min(body.len())..];
    // Only alignment padding may follow: fewer than 4 bytes, all zero, and where the header
    // declares a padding count, exactly that many.
    let padding_ok =
        rest.len() < 4 && rest.iter().all(|&b| b == 0) && declared_padding.is_none_or(|p| p == 0 || p == rest.len());
    if !padding_ok {
        return Err(CodecError::TrailingBytes { type_name, extra: rest.len(), body: used });
    }
    msg.validate().map_err(|reason| CodecError::Invalid { type_name, reason })?;
    Ok(msg)
}
