//! The firmware core and protocol decoder on a real Cortex-M4 instruction set: replays the
//! recorded host session `firmware/qemu/script.bin` through the core (no embassy, no board
//! drivers) and compares every byte the rig answers with `firmware/qemu/expected.bin`, which a
//! host test checks is what the same core produces on the host. Runs under
//! `qemu-system-arm -M mps2-an386 -nographic -semihosting-config enable=on,target=native -kernel`;
//! reports over semihosting and exits with status 0 only on identical output.
//!
//! It also measures the worst stack depth: cortex-m-rt paints the whole stack at reset
//! (`paint-stack`), the simulated rig is built into a static, the stack below is painted again,
//! and after the replay the deepest overwritten word gives the replay's peak use.
#![no_std]
#![no_main]

#[path = "../../../qemu/replay.rs"]
mod replay;

use core::ptr::addr_of;

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};
use static_cell::StaticCell;
use subsurf_firmware::sim::SimRig;

static SCRIPT: &[u8] = include_bytes!("../../../qemu/script.bin");
static EXPECTED: &[u8] = include_bytes!("../../../qemu/expected.bin");

/// cortex-m-rt's `paint-stack` pattern.
const PAINT: u32 = 0xCCCC_CCCC;

unsafe extern "C" {
    /// Lowest stack address (end of `.bss`/`.uninit`), from cortex-m-rt's `link.x`.
    static _stack_end: u32;
    /// Initial stack pointer (top of RAM).
    static _stack_start: u32;
}

fn stack_bounds() -> (usize, usize) {
    // Only the addresses of the linker symbols are taken (no read), which needs no `unsafe`.
    (
        addr_of!(_stack_end) as usize,
        addr_of!(_stack_start) as usize,
    )
}

/// Bytes of stack used so far: from the top down to the deepest word that lost its paint.
fn stack_used() -> usize {
    let (bottom, top) = stack_bounds();
    let mut addr = bottom;
    while addr < top {
        // SAFETY: `bottom..top` is the stack region, word aligned, readable RAM.
        if unsafe { core::ptr::read_volatile(addr as *const u32) } != PAINT {
            break;
        }
        addr += 4;
    }
    top - addr
}

/// Paint the stack from its bottom up to a little below the current stack pointer.
fn repaint() {
    let (bottom, _) = stack_bounds();
    let sp = cortex_m::register::msp::read() as usize;
    let mut addr = bottom;
    while addr + 256 < sp {
        // SAFETY: below the live stack (256 bytes of margin for this function's own frame).
        unsafe { core::ptr::write_volatile(addr as *mut u32, PAINT) };
        addr += 4;
    }
}

/// Build the simulated rig into a static. Not inlined, so its large temporaries live in this
/// frame (gone afterwards), not in `main`'s, which stays live for the whole replay.
#[inline(never)]
fn build_rig() -> &'static mut SimRig {
    static RIG: StaticCell<SimRig> = StaticCell::new();
    RIG.init_with(replay::new_rig)
}

#[entry]
fn main() -> ! {
    let rig = build_rig();
    let startup_stack = stack_used();
    repaint();

    let mut offset = 0usize;
    let mut first_mismatch: Option<usize> = None;
    let mut compare = |chunk: &[u8]| {
        for (i, byte) in chunk.iter().enumerate() {
            if first_mismatch.is_none() && EXPECTED.get(offset + i) != Some(byte) {
                first_mismatch = Some(offset + i);
            }
        }
        offset += chunk.len();
    };
    // Peak stack per record kind (host bytes, e-stop, interlock, ...), repainting before each.
    let mut per_kind = [0usize; 12];
    let mut observe = |kind: u8, done: bool| {
        if done {
            if let Some(peak) = per_kind.get_mut(usize::from(kind)) {
                *peak = (*peak).max(stack_used());
            }
        } else {
            repaint();
        }
    };
    let result = replay::replay_observed(rig, SCRIPT, &mut compare, &mut observe);
    let replay_stack = per_kind.iter().copied().max().unwrap_or(0);
    let (bottom, top) = stack_bounds();

    hprintln!(
        "subsurf-qemu: replay stack peak {} bytes, start-up {} bytes (stack region {} bytes)",
        replay_stack,
        startup_stack,
        top - bottom
    );
    hprintln!(
        "subsurf-qemu: peak by record kind (bytes, e-stop press/release, interlock open/close, \
         advance, pseudo-random session): {:?}",
        &per_kind[..7]
    );
    let ok = match (result, first_mismatch) {
        (Err(e), _) => {
            hprintln!("subsurf-qemu: script error {:?}", e);
            false
        }
        (Ok(_), Some(at)) => {
            hprintln!(
                "subsurf-qemu: output differs from the host's at byte {} (expected {} bytes)",
                at,
                EXPECTED.len()
            );
            false
        }
        (Ok(_), None) if offset != EXPECTED.len() => {
            hprintln!(
                "subsurf-qemu: output is {} bytes, the host's {} bytes",
                offset,
                EXPECTED.len()
            );
            false
        }
        (Ok(records), None) => {
            hprintln!(
                "subsurf-qemu: {} records replayed, {} reply bytes identical to the host core",
                records,
                offset
            );
            true
        }
    };
    debug::exit(if ok {
        debug::EXIT_SUCCESS
    } else {
        debug::EXIT_FAILURE
    });
    #[allow(clippy::empty_loop)]
    loop {}
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    hprintln!("subsurf-qemu: panic: {}", info);
    debug::exit(debug::EXIT_FAILURE);
    #[allow(clippy::empty_loop)]
    loop {}
}
