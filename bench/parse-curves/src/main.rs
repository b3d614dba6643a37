//! Best-of-7 times of reading a batch curve file with `subsurf::curves::read` (parse only),
//! of reading its bytes alone (the floor), and of `curves::read_groups` from memory (as
//! `fit-curve --batch` reads), for BENCHMARKS.md: wall time, and the thread's CPU time where
//! Linux reports it (`/proc/thread-self/schedstat`; steadier than wall time on a loaded
//! machine, but on some kernels only as fine as the scheduler tick).

#[allow(dead_code)]
#[path = "../../../host/src/curves.rs"]
mod curves;

use std::io::Read;
use std::time::Instant;

/// The thread's CPU time so far in seconds, if the kernel reports it.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns: u64 = stat.split_whitespace().next()?.parse().ok()?;
    Some(ns as f64 * 1e-9)
}

/// Best of 7: wall seconds, CPU seconds (NaN where not reported) and `f`'s answer.
fn best(mut f: impl FnMut() -> usize) -> (f64, f64, usize) {
    let (mut wall, mut cpu) = (f64::INFINITY, f64::INFINITY);
    let mut out = 0;
    for _ in 0..7 {
        let (t, c) = (Instant::now(), cpu_seconds());
        out = f();
        wall = wall.min(t.elapsed().as_secs_f64());
        cpu = match (c, cpu_seconds()) {
            (Some(a), Some(b)) => cpu.min(b - a),
            _ => f64::NAN,
        };
    }
    (wall, cpu, out)
}

fn main() {
    let Some(path) = std::env::args().nth(1) else {
        eprintln!("usage: parse-curves FILE.csv");
        std::process::exit(2);
    };
    let open = || std::fs::File::open(&path).expect("open the file");
    let (bytes_s, _, lines) = best(|| {
        let mut f = open();
        let mut buf = vec![0u8; 1 << 20];
        let mut n = 0;
        loop {
            let k = f.read(&mut buf).expect("read");
            if k == 0 {
                break n;
            }
            n += memchr::memchr_iter(b'\n', &buf[..k]).count();
        }
    });
    let (parse_s, _, rows) = best(|| {
        let c = curves::read(open(), true).expect("a batch curve file");
        c.iter().map(|c| c.r.len()).sum()
    });
    // As `fit-curve --batch` reads: curves handed out (and here dropped) a block at a time,
    // from memory, so neither the kernel's copy nor 64 MB of parsed numbers are in the figure.
    let text = std::fs::read(&path).expect("read the file");
    let (grouped_s, grouped_cpu, grouped_rows) = best(|| {
        let mut rows = 0;
        curves::read_groups(&text[..], true, |g| {
            rows += g.iter().map(|c| c.r.len()).sum::<usize>()
        })
        .expect("a batch curve file");
        rows
    });
    println!("read bytes only: {bytes_s:.4} s ({lines} lines)");
    println!(
        "curves::read:    {parse_s:.4} s ({rows} rows, {:.1} ns/row)",
        parse_s / rows as f64 * 1e9
    );
    println!(
        "read_groups, from memory: {grouped_s:.4} s, CPU {grouped_cpu:.4} s ({grouped_rows} rows, {:.1} ns/row)",
        grouped_s / grouped_rows as f64 * 1e9
    );
}
