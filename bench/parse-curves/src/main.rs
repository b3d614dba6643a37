//! Best-of-7 wall time of reading a batch curve file with `subsurf::curves::read` (parse only),
//! and of reading its bytes alone (the floor), for BENCHMARKS.md.

#[allow(dead_code)]
#[path = "../../../host/src/curves.rs"]
mod curves;

use std::io::Read;
use std::time::Instant;

fn best(mut f: impl FnMut() -> usize) -> (f64, usize) {
    let mut best = f64::INFINITY;
    let mut out = 0;
    for _ in 0..7 {
        let t = Instant::now();
        out = f();
        best = best.min(t.elapsed().as_secs_f64());
    }
    (best, out)
}

fn main() {
    let Some(path) = std::env::args().nth(1) else {
        eprintln!("usage: parse-curves FILE.csv");
        std::process::exit(2);
    };
    let open = || std::fs::File::open(&path).expect("open the file");
    let (bytes_s, lines) = best(|| {
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
    let (parse_s, rows) = best(|| {
        let c = curves::read(open(), true).expect("a batch curve file");
        c.iter().map(|c| c.r.len()).sum()
    });
    println!("read bytes only: {bytes_s:.4} s ({lines} lines)");
    println!(
        "curves::read:    {parse_s:.4} s ({rows} rows, {:.1} ns/row)",
        parse_s / rows as f64 * 1e9
    );
}
