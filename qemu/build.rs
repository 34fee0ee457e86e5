//! Links the firmware for QEMU's mps2-an500 (4 MiB of code memory at 0,
//! 4 MiB of RAM at 0x2000_0000) and puts the printer.cfg it runs in
//! `OUT_DIR`: `ONECHIP_QEMU_CONFIG` names the file (default: the golden
//! cartesian machine in `../shared/golden/configs`).

use std::{env, fs, path::PathBuf};

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    fs::write(
        out.join("memory.x"),
        "MEMORY\n{\n  FLASH : ORIGIN = 0x00000000, LENGTH = 4M\n  RAM : ORIGIN = 0x20000000, LENGTH = 4M\n}\n",
    )
    .expect("write memory.x");
    // The interrupt vectors are this crate's own table (src/vectors.rs):
    // nothing for cortex-m-rt's device script to provide.
    fs::write(out.join("device.x"), "").expect("write device.x");
    let manifest = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets it"));
    let config = env::var_os("ONECHIP_QEMU_CONFIG").map_or_else(
        || manifest.join("../../shared/golden/configs/cartesian.cfg"),
        PathBuf::from,
    );
    let text = fs::read(&config)
        .unwrap_or_else(|e| panic!("ONECHIP_QEMU_CONFIG {}: {e}", config.display()));
    fs::write(out.join("printer.cfg"), text).expect("write printer.cfg");
    println!("cargo:rerun-if-env-changed=ONECHIP_QEMU_CONFIG");
    println!("cargo:rerun-if-changed={}", config.display());
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
}
