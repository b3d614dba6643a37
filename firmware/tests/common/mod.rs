//! The one minimal host the firmware core's tests drive the simulated rig with: numbered requests
//! over the unframed core, replies returned, events collected. Each test file adds its own
//! timing helpers (`advance`) in its own `impl Host`.
#![allow(dead_code)]

use subsurf_firmware::sim::{SimParams, SimRig};
use subsurf_protocol::*;

/// A minimal host: numbered requests, collected events.
pub struct Host {
    pub sim: SimRig,
    pub seq: Seq,
    pub events: Vec<Event>,
}

impl Host {
    /// A rig with an open session (`Hello` answered).
    pub fn new(params: SimParams) -> Self {
        let mut h = Self::without_hello(params);
        let hello = h.call(Command::Hello {
            protocol_version: PROTOCOL_VERSION,
        });
        assert!(matches!(hello, Ok(Response::Hello(_))), "{hello:?}");
        h
    }

    /// A freshly booted rig, no session yet.
    pub fn without_hello(params: SimParams) -> Self {
        Self {
            sim: SimRig::new(params),
            seq: 0,
            events: Vec::new(),
        }
    }

    /// One request with an explicit `seq` (retransmissions reuse one); the replies it produced.
    pub fn send(&mut self, seq: Seq, command: Command) -> Vec<Reply> {
        let now = self.sim.now();
        self.sim
            .rig_mut()
            .handle_request(now, Request { seq, command });
        self.collect()
    }

    /// Drains the rig's output: replies returned, events kept in `events`.
    pub fn collect(&mut self) -> Vec<Reply> {
        let mut replies = Vec::new();
        while let Some(msg) = self.sim.rig_mut().poll_message() {
            match msg {
                RigMessage::Reply(r) => replies.push(r),
                RigMessage::Event(e) => self.events.push(e),
            }
        }
        replies
    }

    /// The next numbered request; exactly one reply, to it.
    pub fn call(&mut self, command: Command) -> Result<Response, RigError> {
        self.seq += 1;
        let replies = self.send(self.seq, command);
        assert_eq!(replies.len(), 1);
        assert_eq!(replies[0].seq, self.seq);
        replies[0].result.clone()
    }
}
