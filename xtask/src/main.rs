//! Firmware image tools, run as `cargo xtask <command>`.
//!
//! `cargo xtask image [ELF]` checks the firmware ELF built by `cargo fw`
//! (under `$CARGO_TARGET_DIR` if set, else `target/`) against
//! `board/budget.toml` (flash and static RAM budgets, application base
//! address, stepper interrupt vector, linked and forbidden code) and the
//! rules of [`checks`] (stack below the statics, start-up taking control,
//! safe panic and fault paths), [`stack_use`] (a static worst-case
//! stack estimate) and [`tcm`] (the stepper interrupt in ITCM/DTCM, DMA
//! buffers non-cacheable, caches on the boot path), and writes
//! `firmware.bin` next to it, ready
//! for the board's SD-card bootloader. Exits non-zero on any violation,
//! with the reason.
//!
//! `cargo xtask hour-print DIR [--hours N]` writes an SD folder for the
//! host build's speed benchmark: the golden cartesian machine and an
//! N-hour print (one by default) made of the golden extrusion case's body
//! repeated (`time cargo sim DIR`).
//!
//! `cargo xtask sim-memory` checks that the host build's peak memory does
//! not grow with the print ([`sim_memory`]).

mod bench_print;
mod budget;
mod call_graph;
mod checks;
mod elf_image;
#[cfg(target_os = "linux")]
mod sim_memory;
mod stack_use;
mod tcm;
mod thumb;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// The firmware ELF under the target directory.
const ELF_IN_TARGET: &str = "thumbv7em-none-eabihf/release/onechip-board";
const BUDGET: &str = "board/budget.toml";
const USAGE: &str = "usage: cargo xtask image [ELF] | cargo xtask hour-print DIR [--hours N] | cargo xtask sim-memory";

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("image") => image(&args.get(1).map_or_else(default_elf, PathBuf::from)),
        Some("hour-print") => bench_print::parse_args(&args[1..])
            .and_then(|(dir, hours)| bench_print::write(&workspace_root(), &dir, hours)),
        Some("sim-memory") => sim_memory(),
        _ => Err(USAGE.into()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("xtask: {e}");
            ExitCode::FAILURE
        }
    }
}

/// The ELF `cargo fw` builds.
fn default_elf() -> PathBuf {
    target_dir().join(ELF_IN_TARGET)
}

/// Cargo's target directory: `$CARGO_TARGET_DIR` (relative to the current
/// directory, as cargo takes it) if set, else the workspace's `target/`.
fn target_dir() -> PathBuf {
    match std::env::var_os("CARGO_TARGET_DIR") {
        Some(dir) => std::env::current_dir().unwrap_or_default().join(dir),
        None => workspace_root().join("target"),
    }
}

/// Measures the host build's peak memory on prints of two lengths.
#[cfg(target_os = "linux")]
fn sim_memory() -> Result<(), String> {
    sim_memory::run(&workspace_root(), &target_dir())
}

/// Peak memory is read with Linux's `wait4`.
#[cfg(not(target_os = "linux"))]
fn sim_memory() -> Result<(), String> {
    Err("sim-memory reads peak memory on Linux only".into())
}

/// Checks the firmware image and writes firmware.bin beside the ELF.
fn image(elf_path: &Path) -> Result<(), String> {
    let root = workspace_root();
    let mut budget = budget::Budget::load(&root.join(BUDGET))?;
    let elf_path = root.join(elf_path);
    let data = std::fs::read(&elf_path)
        .map_err(|e| format!("{}: {e} (build it with `cargo fw`)", elf_path.display()))?;
    let image = elf_image::Image::parse(&data)?;
    budget.select_layout(image.vector_table_address()?)?;

    let flash = image.flash_bytes();
    // DTCM has a budget of its own (dtcm_kib, the linker's region): the
    // RAM budget is the AXI SRAM's, whose statics share it with the stack.
    let dtcm = budget.dtcm_base..budget.dtcm_base + budget.dtcm_kib * 1024;
    let in_dtcm: u64 = (image.ram_sections().iter())
        .filter(|s| dtcm.contains(&s.addr))
        .map(|s| s.size)
        .sum();
    let ram = image.static_ram_bytes() - in_dtcm;
    println!("firmware: {}", elf_path.display());
    println!(
        "flash: {:>7} bytes ({:.1} KiB of {} KiB budget)",
        flash,
        kib(flash),
        budget.flash_kib
    );
    println!(
        "ram:   {:>7} bytes ({:.1} KiB of {} KiB budget, static: every RAM section but DTCM's)",
        ram,
        kib(ram),
        budget.ram_kib
    );
    println!(
        "dtcm:  {:>7} bytes ({:.1} KiB of {} KiB)",
        in_dtcm,
        kib(in_dtcm),
        budget.dtcm_kib
    );

    let mut problems = Vec::new();
    if flash > budget.flash_kib * 1024 {
        problems.push(format!(
            "flash {flash} bytes exceeds {} KiB",
            budget.flash_kib
        ));
    }
    if ram > budget.ram_kib * 1024 {
        problems.push(format!(
            "static RAM {ram} bytes exceeds {} KiB",
            budget.ram_kib
        ));
    }
    if in_dtcm > budget.dtcm_kib * 1024 {
        problems.push(format!(
            "DTCM statics {in_dtcm} bytes exceed {} KiB",
            budget.dtcm_kib
        ));
    }
    match image.interrupt_handler(budget.stepper_irq_number) {
        Ok(handler) => {
            let expected = image.symbol(&budget.stepper_irq)?;
            if handler == expected {
                println!(
                    "vector: IRQ {} -> {} at {handler:#010x}",
                    budget.stepper_irq_number, budget.stepper_irq
                );
            } else {
                problems.push(format!(
                    "vector table entry {} is {handler:#010x}, not {} at {expected:#010x}",
                    budget.stepper_irq_number, budget.stepper_irq
                ));
            }
        }
        Err(e) => problems.push(e),
    }
    for fragment in &budget.required_code {
        if image.has_symbol_containing(fragment) {
            println!("linked: {fragment}");
        } else {
            problems.push(format!("no code matching `{fragment}` is linked in"));
        }
    }
    let rules: [(&str, checks::Check); 6] = [
        ("stack", checks::stack),
        ("stack use", stack_use::check),
        ("tcm", tcm::check),
        ("reset", checks::reset),
        ("forbidden", checks::forbidden),
        ("safety", |image, _| checks::safety(image)),
    ];
    for (name, check) in rules {
        match check(&image, &budget) {
            Ok(found) => println!("{name}: {found}"),
            Err(e) => problems.push(format!("{name}: {e}")),
        }
    }
    match image.flat_binary(budget.app_base) {
        Ok(bin) => {
            let bin_path = elf_path.with_file_name("firmware.bin");
            std::fs::write(&bin_path, &bin).map_err(|e| format!("{}: {e}", bin_path.display()))?;
            println!(
                "image: {} ({} bytes at {:#010x})",
                bin_path.display(),
                bin.len(),
                budget.app_base
            );
        }
        Err(e) => problems.push(e),
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(problems.join("; "))
    }
}

fn kib(bytes: u64) -> f64 {
    bytes as f64 / 1024.0
}

/// The workspace root (this crate lives in `<root>/xtask`).
fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
}
