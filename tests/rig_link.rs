//! The host's rig client against the simulated rig over faulty links: in memory with virtual time,
//! and over a real pseudo-terminal pair.

use std::time::Duration;

use crate::harness::{PtyRig, check_exactly_once, lossy_client_config, run_script, virtual_rig};
use subsurf::link::{FaultConfig, MemoryLink};
use subsurf::rig::{RigClient, RigClientError};
use subsurf_protocol::{Capture, Command, EventKind, GalvoPoint, ProgramHeader, RigError};

/// The lossy link's acceptance scenario: 1% of bytes dropped, 1% corrupted, 1% of frames duplicated,
/// both directions; 10,000 commands; every one executed exactly once, in order. Lost events are
/// replayed: every capture's `Captured` report reaches the script, once, in order.
#[test]
fn ten_thousand_commands_over_a_lossy_link_run_exactly_once_in_order() {
    let mut rig = virtual_rig(FaultConfig::lossy(1), FaultConfig::lossy(2)).expect("connect");
    let log = run_script(&mut rig, 10_000).expect("script");
    let stats = rig.stats();
    let (to_rig, to_host) = rig.link().fault_stats();
    // The faults really happened, and the client really had to work around them.
    assert!(to_rig.dropped > 100 && to_rig.corrupted > 100 && to_rig.duplicated_frames > 10);
    assert!(to_host.dropped > 100 && to_host.corrupted > 100 && to_host.duplicated_frames > 10);
    assert!(stats.retransmits > 500, "{stats:?}");
    assert!(stats.requests >= 10_000, "{stats:?}");
    check_exactly_once(&log, rig.link().rig());
    // Events were lost on the link, and every one of them was recovered.
    assert!(stats.lost_events > 10, "{stats:?}");
    assert_eq!(stats.recovered_events, stats.lost_events, "{stats:?}");
    assert_eq!(stats.gone_events, 0, "{stats:?}");
    assert_eq!(log.lost_capture_events, 0);
    assert_eq!(
        log.captured, log.capture_ids,
        "every Captured once, in order"
    );
    assert_eq!(log.captured.len(), 100);
}

/// A queued program over the lossy wire: the caller sees every event of the session exactly
/// once, in `event_seq` order, and one `Captured` per point, although the wire lost many.
#[test]
fn lossy_program_delivers_every_event_once_in_order() {
    let mut rig = virtual_rig(FaultConfig::lossy(5), FaultConfig::lossy(6)).expect("connect");
    let first_event = rig.status().expect("status").next_event_seq;
    let n: u16 = 150;
    let points: Vec<GalvoPoint> = (0..n).map(|i| GalvoPoint { x: i, y: 7 }).collect();
    rig.arm().expect("arm");
    let header = ProgramHeader {
        len: n,
        channel: 0,
        settle_us: Some(10),
        exposure_us: 200,
        trigger_us: 20,
        // A 50 frames/s camera: faster than replays get through this noisy a line (2% of
        // bytes hit), the rig's event history would run over.
        interval_us: 20_000,
    };
    rig.load_program(header, &points).expect("load");
    let first = rig.run_program().expect("run");
    let mut seqs = Vec::new();
    let mut ids = Vec::new();
    loop {
        let event = rig
            .next_event(Duration::from_secs(60))
            .expect("pump")
            .expect("an event");
        seqs.push(event.event_seq);
        match event.kind {
            EventKind::Captured(c) => ids.push(c.capture_id),
            EventKind::ProgramDone { finished, .. } => {
                assert!(finished);
                break;
            }
            other => panic!("unexpected event {other:?}"),
        }
    }
    let expected: Vec<u32> = (0..=u32::from(n)).map(|i| first_event + i).collect();
    assert_eq!(
        seqs,
        expected,
        "every event once, in order: {:?}",
        rig.stats()
    );
    let want: Vec<u32> = (0..u32::from(n)).map(|i| first.wrapping_add(i)).collect();
    assert_eq!(ids, want);
    let stats = rig.stats();
    assert!(stats.lost_events > 5 && stats.replays > 0, "{stats:?}");
    assert_eq!(
        (stats.recovered_events, stats.gone_events),
        (stats.lost_events, 0),
        "{stats:?}"
    );
}

/// Events a rig sent to an earlier session never reach a new one: the new client drops what
/// arrives before its handshake's status.
#[test]
fn a_new_session_gets_no_stale_events() {
    let mut rig = virtual_rig(FaultConfig::clean(), FaultConfig::clean()).expect("connect");
    rig.arm().expect("arm");
    rig.start_capture(Capture {
        galvo: GalvoPoint { x: 1, y: 1 },
        settle_us: Some(10),
        channel: 0,
        exposure_us: 100,
        trigger_us: 10,
    })
    .expect("capture");
    // The host vanishes mid-capture; the rig finishes it, then halts on the lost heartbeat,
    // and its `Captured` and `Halted` events wait on the wire for whoever connects next.
    let timeout = u64::from(rig.get_config().expect("config").heartbeat_timeout_ms);
    let mut link = rig.into_link();
    link.advance(Duration::from_millis(timeout * 2));
    let mut rig =
        RigClient::connect_with_seq(link, lossy_client_config(Duration::from_millis(20)), 77)
            .expect("reconnect");
    assert!(rig.stats().stale_events >= 2, "{:?}", rig.stats());
    assert_eq!(
        rig.next_event(Duration::from_millis(50)).expect("pump"),
        None
    );
}

#[test]
fn the_same_seed_gives_the_same_session() {
    let run = || {
        let mut rig = virtual_rig(FaultConfig::lossy(9), FaultConfig::lossy(10)).expect("connect");
        let log = run_script(&mut rig, 300).expect("script");
        (log, rig.stats(), rig.link().elapsed())
    };
    assert_eq!(run(), run());
}

#[test]
fn lossy_pty_session_runs_exactly_once_in_order() {
    let mut pty = PtyRig::start(
        FaultConfig::lossy(3),
        FaultConfig::lossy(4),
        Duration::from_millis(3),
    )
    .expect("pty rig");
    let log = run_script(&mut pty.client, 1_500).expect("script");
    assert!(pty.client.stats().retransmits > 50);
    pty.server.with_rig(|rig| check_exactly_once(&log, rig));
}

#[test]
fn clean_pty_session_runs_exactly_once_in_order() {
    let mut pty = PtyRig::start(
        FaultConfig::clean(),
        FaultConfig::clean(),
        // Long enough that a loaded machine causes no spurious retransmission.
        Duration::from_secs(1),
    )
    .expect("pty rig");
    let log = run_script(&mut pty.client, 2_000).expect("script");
    assert_eq!(pty.client.stats().retransmits, 0);
    assert_eq!(log.lost_capture_events, 0);
    pty.server.with_rig(|rig| check_exactly_once(&log, rig));
}

#[test]
fn garbage_on_the_pty_is_survived() {
    let mut pty = PtyRig::start(
        FaultConfig::clean(),
        FaultConfig::clean(),
        Duration::from_millis(20),
    )
    .expect("pty rig");
    let before = pty.client.status().expect("status").rx_dropped;
    // A second writer on the same line spews noise, with and without delimiters.
    let junk: Vec<u8> = (0..5000u32).map(|i| (i * 7919 % 251) as u8).collect();
    pty.inject(&junk).expect("noise");
    pty.inject(&[0xff; 600]).expect("oversize run");
    pty.inject(&[0]).expect("delimiter");
    pty.client.galvo(5, 6).expect("galvo after noise");
    let s = pty.client.status().expect("status after noise");
    assert_eq!(s.galvo, GalvoPoint { x: 5, y: 6 });
    assert!(s.rx_dropped > before, "the rig counted the garbage");
}

#[test]
fn unknown_protocol_version_is_refused() {
    let mut rig = virtual_rig(FaultConfig::clean(), FaultConfig::clean()).expect("connect");
    let reply = rig
        .call_raw(Command::Hello {
            protocol_version: subsurf_protocol::PROTOCOL_VERSION + 1,
        })
        .expect("a reply");
    assert_eq!(
        reply,
        Err(RigError::UnknownVersion {
            rig: subsurf_protocol::PROTOCOL_VERSION
        })
    );
}

#[test]
fn a_silent_rig_is_a_clear_error() {
    let (host, _rig_end) = MemoryLink::pair(FaultConfig::clean(), FaultConfig::clean());
    let mut config = lossy_client_config(Duration::from_millis(5));
    config.give_up_after = Duration::from_millis(50);
    let err = RigClient::connect(host, config).expect_err("nobody answers");
    assert!(matches!(err, RigClientError::NoReply { .. }), "{err}");
    assert!(err.to_string().contains("no reply"), "{err}");
}

#[test]
fn heartbeats_keep_the_rig_armed_and_silence_disarms_it() {
    let mut rig = virtual_rig(FaultConfig::clean(), FaultConfig::clean()).expect("connect");
    let timeout = u64::from(rig.get_config().expect("config").heartbeat_timeout_ms);
    rig.arm().expect("arm");
    // The client pumps (and heartbeats) for ten heartbeat timeouts of virtual time.
    rig.poll(Duration::from_millis(timeout * 10)).expect("poll");
    assert!(
        rig.status().expect("status").armed,
        "heartbeats kept it armed"
    );
    // The host goes silent.
    let mut link = rig.into_link();
    link.advance(Duration::from_millis(timeout * 2));
    let mut rig =
        RigClient::connect_with_seq(link, lossy_client_config(Duration::from_millis(20)), 5)
            .expect("reconnect");
    assert!(
        !rig.status().expect("status").armed,
        "heartbeat loss disarmed"
    );
}

#[test]
fn capture_program_streams_one_event_per_point_in_order() {
    let mut rig = virtual_rig(FaultConfig::clean(), FaultConfig::clean()).expect("connect");
    let caps = rig.hello().capabilities;
    let n = caps.max_program_points.min(200);
    let points: Vec<GalvoPoint> = (0..n).map(|i| GalvoPoint { x: i, y: n - i }).collect();
    rig.arm().expect("arm");
    let header = ProgramHeader {
        len: n,
        channel: 0,
        settle_us: None,
        exposure_us: 1000,
        trigger_us: 100,
        interval_us: 12_000,
    };
    rig.load_program(header, &points).expect("load");
    let first = rig.run_program().expect("run");
    let mut seen = Vec::new();
    loop {
        let event = rig
            .next_event(Duration::from_secs(60))
            .expect("pump")
            .expect("an event");
        match event.kind {
            EventKind::Captured(c) => seen.push(c),
            EventKind::ProgramDone {
                completed,
                finished,
            } => {
                assert!(finished);
                assert_eq!(completed, n);
                break;
            }
            EventKind::Halted { reason } => panic!("halted: {reason:?}"),
            _ => {}
        }
    }
    assert_eq!(seen.len(), usize::from(n));
    for (i, c) in seen.iter().enumerate() {
        assert_eq!(c.capture_id, first.wrapping_add(i as u32));
        assert_eq!(c.program_index, Some(i as u16));
        assert_eq!(c.galvo, points[i]);
    }
    // Equal one-code jumps after the first point: captures start exactly interval_us apart,
    // and the camera confirmed and counted every one.
    assert!(
        seen[1..]
            .windows(2)
            .all(|w| w[1].triggered_at_us - w[0].triggered_at_us == 12_000)
    );
    assert!(
        seen.windows(2)
            .all(|w| w[1].exposure_count == w[0].exposure_count + 1 && w[1].lit)
    );
    assert_eq!(rig.link().rig().triggers().len(), usize::from(n));
}
