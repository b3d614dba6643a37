//! Every message between the subsurf host and the rig, and how it is framed on the wire.
//!
//! Contract: `no_std`, no allocation, no I/O, no panics reachable from input.
//!
//! - Host → rig: [`Request`] (a [`Seq`] plus a [`Command`]), encoded with [`encode_request`].
//! - Rig → host: [`RigMessage`] — a [`Reply`] echoing the request's `seq`, or an unsolicited
//!   [`Event`] — encoded with [`encode_reply`] / [`encode_event`].
//! - Both directions: a [`FrameDecoder`] turns arbitrary byte chunks into messages.
//!
//! The wire format (postcard + CRC-32 + COBS, 0-delimited, at most [`MAX_FRAME`] bytes) and the
//! sequence/retransmission rules are specified in `docs/protocol.md`.
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]
#![cfg_attr(
    not(test),
    deny(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing
    )
)]

mod frame;
mod message;
mod profile;

pub use frame::{
    CRC_LEN, DecoderStats, DropReason, EncodeError, FrameDecoder, Frames, MAX_FRAME, MAX_MESSAGE,
    decode_frame, encode_event, encode_frame, encode_reply, encode_request,
};
pub use message::*;
pub use profile::*;
