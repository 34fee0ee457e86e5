//! Puts this board's memory map where the linker finds it and links the
//! firmware with cortex-m-rt's and defmt's linker scripts. With the
//! feature `no-bootloader` the application takes the whole flash from
//! 0x08000000 instead of following BTT's bootloader.

use std::{env, fs, path::PathBuf};

/// memory.x's flash region: after BTT's 128 KiB bootloader.
const AFTER_BOOTLOADER: &str = "FLASH : ORIGIN = 0x08020000, LENGTH = 512K - 128K";
/// The flash region without a bootloader.
const WHOLE_FLASH: &str = "FLASH : ORIGIN = 0x08000000, LENGTH = 512K";

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let memory = include_str!("memory.x");
    assert!(
        memory.contains(AFTER_BOOTLOADER),
        "memory.x: no `{AFTER_BOOTLOADER}` line to lay out"
    );
    let memory = if env::var_os("CARGO_FEATURE_NO_BOOTLOADER").is_some() {
        memory.replace(AFTER_BOOTLOADER, WHOLE_FLASH)
    } else {
        memory.to_string()
    };
    fs::write(out.join("memory.x"), memory).expect("write memory.x");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rustc-link-arg-bins=--nmagic");
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
    println!("cargo:rustc-link-arg-bins=-Tdefmt.x");
}
