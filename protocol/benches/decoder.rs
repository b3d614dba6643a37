//! Decoder and encoder throughput: `cargo bench -p subsurf-protocol`.
//!
//! The stream mixes the message shapes a scan produces (capture events, status replies, program
//! chunks) and is fed in 64-byte chunks, as a UART DMA buffer would deliver it.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use std::hint::black_box;
use subsurf_protocol::*;

fn stream() -> (Vec<u8>, usize) {
    let mut out = Vec::new();
    let mut buf = [0u8; MAX_FRAME];
    let mut frames = 0;
    for i in 0..1000u32 {
        let msg = match i % 3 {
            0 => RigMessage::Event(Event {
                event_seq: i,
                timestamp_us: 1_000_000 + u64::from(i) * 3_000,
                kind: EventKind::Captured(Captured {
                    capture_id: i,
                    program_index: Some(i as u16),
                    triggered_at_us: u64::from(i) * 3_000,
                    exposure: Some(ExposureActive {
                        delay_us: 15,
                        duration_us: 1_000,
                    }),
                    exposure_count: i,
                    lit: true,
                    galvo: GalvoPoint {
                        x: (i * 37) as u16,
                        y: (i * 91) as u16,
                    },
                    channel: 1,
                }),
            }),
            1 => RigMessage::Reply(Reply {
                seq: i,
                result: Ok(Response::Ack),
            }),
            _ => RigMessage::Reply(Reply {
                seq: i,
                result: Ok(Response::Status(Status {
                    boot_nonce: 0x5eed_0001,
                    exposures: i,
                    state: RigState::Program,
                    position: -12_345,
                    homed: true,
                    armed: true,
                    lasers: 2,
                    galvo: GalvoPoint {
                        x: 40_000,
                        y: 1_000,
                    },
                    inputs: Inputs {
                        estop: false,
                        interlock_closed: true,
                        home_switch: false,
                    },
                    fault: None,
                    next_capture_id: i,
                    next_event_seq: i,
                    program_received: 512,
                    program_len: 512,
                    rx_dropped: 0,
                    uptime_us: 123_456_789,
                })),
            }),
        };
        let n = encode_frame(&msg, &mut buf).unwrap_or(0);
        out.extend_from_slice(&buf[..n]);
        frames += 1;
    }
    (out, frames)
}

fn program_chunk() -> Request {
    let points = (0..PROGRAM_CHUNK as u16).map(|i| GalvoPoint {
        x: i * 1_999,
        y: 65_000 - i,
    });
    Request {
        seq: 77,
        command: Command::ProgramPoints(ProgramChunk {
            offset: 64,
            points: points.collect(),
        }),
    }
}

fn bench(c: &mut Criterion) {
    let (bytes, frames) = stream();
    let mut group = c.benchmark_group("decoder");
    group.throughput(Throughput::Bytes(bytes.len() as u64));
    group.bench_function("mixed_rig_stream_64B_chunks", |b| {
        b.iter(|| {
            let mut dec = FrameDecoder::new();
            let mut n = 0;
            for chunk in black_box(&bytes).chunks(64) {
                n += dec.decode::<RigMessage>(chunk).count();
            }
            assert_eq!(n, frames);
        })
    });
    let mut req_bytes = Vec::new();
    let mut buf = [0u8; MAX_FRAME];
    for _ in 0..200 {
        let n = encode_request(&program_chunk(), &mut buf).unwrap_or(0);
        req_bytes.extend_from_slice(&buf[..n]);
    }
    group.throughput(Throughput::Bytes(req_bytes.len() as u64));
    group.bench_function("program_chunks_64B_chunks", |b| {
        b.iter(|| {
            let mut dec = FrameDecoder::new();
            let mut n = 0;
            for chunk in black_box(&req_bytes).chunks(64) {
                n += dec.decode::<Request>(chunk).count();
            }
            assert_eq!(n, 200);
        })
    });
    group.finish();

    let mut group = c.benchmark_group("encoder");
    let req = program_chunk();
    let n = encode_request(&req, &mut buf).unwrap_or(0);
    group.throughput(Throughput::Bytes(n as u64));
    group.bench_function("program_chunk", |b| {
        b.iter(|| encode_request(black_box(&req), &mut buf))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
