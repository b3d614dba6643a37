//! 10,000 commands over a link that drops 1 % of bytes, corrupts 1 % of bytes and duplicates 1 % of
//! frames, in both directions: with stop-and-wait retransmission every command is executed exactly
//! once and in order (the rig answers retransmissions from its reply cache).

use subsurf_firmware::sim::SimRig;
use subsurf_protocol::*;

/// xorshift64*: deterministic faults without a dependency.
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    fn percent(&mut self, p: u64) -> bool {
        self.next() % 100 < p
    }

    /// One frame through the faulty wire.
    fn pass(&mut self, frame: &[u8], out: &mut Vec<u8>) {
        let copies = if self.percent(1) { 2 } else { 1 };
        for _ in 0..copies {
            for &b in frame {
                if self.percent(1) {
                    continue;
                }
                if self.percent(1) {
                    out.push(b ^ (1 + (self.next() % 255) as u8));
                } else {
                    out.push(b);
                }
            }
        }
    }
}

#[test]
fn ten_thousand_commands_exactly_once_in_order() {
    const N: u32 = 10_000;
    const RETRANSMIT_US: u64 = 3_000;
    let mut sim = SimRig::default();
    let mut noise = Noise(0x5eed_1234_abcd_9876);
    let mut host_rx = FrameDecoder::new();
    let mut frame = [0u8; MAX_FRAME];
    let mut retransmits = 0u32;
    let point = |i: u32| GalvoPoint {
        x: (i % 65_536) as u16,
        y: (i / 65_536) as u16,
    };
    for i in 0..N {
        // Seq numbers start high to cross the u32 wrap in the middle of the run.
        let seq = (u32::MAX - N / 2).wrapping_add(i);
        let command = if i == 0 {
            Command::Hello {
                protocol_version: PROTOCOL_VERSION,
            }
        } else {
            Command::Galvo(point(i))
        };
        let n = encode_request(&Request { seq, command }, &mut frame).unwrap();
        let mut sent_at = sim.now();
        let mut wire = Vec::new();
        noise.pass(&frame[..n], &mut wire);
        loop {
            let now = sim.now() + 200;
            sim.feed(now, &wire);
            wire.clear();
            let mut back = Vec::new();
            sim.drain_frames(|f| noise.pass(f, &mut back));
            let replies: Vec<RigMessage> = host_rx.decode(&back).collect();
            if let Some(reply) = replies.iter().find_map(|m| match m {
                RigMessage::Reply(r) if r.seq == seq => Some(r),
                _ => None,
            }) {
                assert!(reply.result.is_ok(), "command {i}: {:?}", reply.result);
                break;
            }
            if sim.now() - sent_at >= RETRANSMIT_US {
                retransmits += 1;
                sent_at = sim.now();
                // A lone delimiter first flushes any garbage the rig has buffered.
                wire.push(0);
                noise.pass(&frame[..n], &mut wire);
            }
        }
        if i > 0 {
            // In order: the command just acknowledged is the latest one executed.
            assert_eq!(sim.hw().galvo(), point(i), "command {i}");
        }
    }
    // Exactly once: one galvo write at boot plus one per Galvo command, despite retransmissions.
    assert_eq!(sim.hw().galvo_log().total(), u64::from(N));
    assert!(
        retransmits > 50,
        "the link should have forced retransmissions ({retransmits})"
    );
    eprintln!(
        "retransmits {retransmits}, rig drops {:?}, host drops {:?}",
        sim.rig().rx_stats(),
        host_rx.stats()
    );
    assert!(sim.rig().rx_stats().dropped() > 50);
    assert!(host_rx.stats().dropped() > 50);
}
