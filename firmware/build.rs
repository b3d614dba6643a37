//! Linker set-up for the two bare-metal binaries; host builds (the core, its tests) get nothing.
//!
//! - `subsurf-board` (feature `board`): cortex-m-rt's `link.x` and defmt's `defmt.x` with
//!   `board/memory.x` (the chip's map, code after the profile's flash sectors).
//! - `subsurf-qemu` and `subsurf-qemu-isr` (feature `qemu`): `link.x` with `qemu/memory.x`
//!   (QEMU's mps2-an386 map).
use std::env;

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=qemu/memory.x");
    println!("cargo:rerun-if-changed=board/memory.x");
    if env::var("CARGO_CFG_TARGET_OS").as_deref() != Ok("none") {
        return;
    }
    let board = env::var_os("CARGO_FEATURE_BOARD").is_some();
    let qemu = env::var_os("CARGO_FEATURE_QEMU").is_some();
    if board && qemu {
        // Two memory.x files would be on the linker path; the build would link the wrong map.
        panic!("features `board` and `qemu` are separate builds: enable one of them");
    }
    if board {
        let dir = env::var("CARGO_MANIFEST_DIR").unwrap_or_default();
        println!("cargo:rustc-link-search={dir}/board");
        println!("cargo:rustc-link-arg-bin=subsurf-board=--nmagic");
        println!("cargo:rustc-link-arg-bin=subsurf-board=-Tlink.x");
        println!("cargo:rustc-link-arg-bin=subsurf-board=-Tdefmt.x");
    }
    if qemu {
        let dir = env::var("CARGO_MANIFEST_DIR").unwrap_or_default();
        println!("cargo:rustc-link-search={dir}/qemu");
        println!("cargo:rustc-link-arg-bin=subsurf-qemu=-Tlink.x");
        println!("cargo:rustc-link-arg-bin=subsurf-qemu-isr=-Tlink.x");
    }
}
