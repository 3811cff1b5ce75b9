//! labrig-openpi: openpi's policy protocol and DROID's action conventions, with no ROS and no
//! torch in it, so the loop (a client) and the policy server (a server) share one codec.
//!
//! - [`codec`]: msgpack with numpy arrays as openpi's `msgpack_numpy` packs them.
//! - [`client`]: `Client::connect` reads the server's metadata frame; `infer` is one request
//!   and one reply; an error frame, a close or a timeout is named and ends the connection.
//! - [`server`]: `Server::bind` answers openpi clients (metadata, `server_timing`, `/healthz`,
//!   error frames with close 1011).
//! - [`droid`]: DROID's observation keys, `resize_with_pad`, and the 15 Hz joint-velocity chunk
//!   resampled into joint targets at the loop's period.

pub mod client;
pub mod codec;
pub mod droid;
pub mod server;

pub use client::{Client, ClientError};
pub use codec::{Array, Value};
pub use server::{Handler, Server};
