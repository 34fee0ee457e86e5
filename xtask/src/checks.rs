//! The firmware image's start-up, stack and safety rules, checked on the
//! ELF (board/ runs only on the target, so these are its tests).
//!
//! Each check returns what it found (printed) or why the image breaks the
//! rule (a CI failure).

use crate::budget::Budget;
use crate::elf_image::Image;
use crate::thumb::{self, CPSID_I, CPSIE_I};

/// Cortex-M7 registers the start-up code must write.
const VTOR: u32 = 0xe000_ed08;
const NVIC_ICER0: u32 = 0xe000_e180;
const NVIC_ICPR0: u32 = 0xe000_e280;
const SYST_CSR: u32 = 0xe000_e010;

/// Vector table entries of the faults and NMI (2: NMI .. 6: UsageFault).
const FAULT_VECTORS: [(u64, &str); 5] = [
    (2, "NMI"),
    (3, "HardFault"),
    (4, "MemManage"),
    (5, "BusFault"),
    (6, "UsageFault"),
];

/// A rule on the image: what it found, or why the image breaks it.
pub type Check = fn(&Image<'_>, &Budget) -> Result<String, String>;

/// Calls followed from a handler to the safe-off function.
const CALL_DEPTH: usize = 4;

/// `stack`: the stack lies between `ram_base` (nothing mapped below) and
/// the statics of its RAM bank, so an overflow faults instead of
/// overwriting them, and is at least `stack_kib`. (Statics in memories
/// below `ram_base`, the DTCM, are out of the overflow's way.)
pub fn stack(image: &Image<'_>, budget: &Budget) -> Result<String, String> {
    let top = image.vector(0)?;
    let base = budget.ram_base;
    if top < base {
        return Err(format!(
            "the initial stack pointer {top:#010x} lies below the RAM base {base:#010x}"
        ));
    }
    let sections: Vec<_> = image
        .ram_sections()
        .iter()
        .filter(|s| s.addr >= base)
        .collect();
    if let Some(s) = sections.iter().find(|s| s.addr < top) {
        return Err(format!(
            "{} at {:#010x} lies below the initial stack pointer {top:#010x}: a stack \
             overflow would overwrite it (the stack must sit below the statics, see \
             board/memory.x)",
            s.name, s.addr
        ));
    }
    let size = top - base;
    if size < budget.stack_kib * 1024 {
        return Err(format!(
            "the stack is {size} bytes, less than {} KiB",
            budget.stack_kib
        ));
    }
    let end = sections
        .iter()
        .map(|s| s.addr + s.size)
        .max()
        .unwrap_or(top);
    Ok(format!(
        "{:.1} KiB at {base:#010x}..{top:#010x}, below the statics ({top:#010x}..{end:#010x}); \
         an overflow faults below {base:#010x}",
        size as f64 / 1024.0
    ))
}

/// `reset`: the reset handler calls `__pre_init` first, which masks
/// interrupts, sets SP to the vector table's initial stack pointer and
/// VTOR to the vector table, clears the NVIC's enables and pending bits
/// and stops SysTick, then unmasks interrupts.
pub fn reset(image: &Image<'_>, budget: &Budget) -> Result<String, String> {
    let reset = image
        .function_at(image.vector(1)?)
        .ok_or("the reset vector points at no function")?;
    let pre_init = image.function("__pre_init")?;
    let reset_insns = image.instructions(reset)?;
    if reset_insns.first().and_then(|i| i.branch) != Some(pre_init.addr) {
        return Err(format!("`{}` does not call __pre_init first", reset.name));
    }
    let insns = image.instructions(pre_init)?;
    let words = image.words(pre_init)?;
    let mut missing = Vec::new();
    if insns.first().map(|i| i.hw1) != Some(CPSID_I) {
        missing.push("cpsid i first".to_string());
    }
    let sp = image.vector(0)? as u32;
    if !insns.iter().any(thumb::is_msr_msp) || !words.contains(&sp) {
        missing.push(format!("SP set to {sp:#010x}"));
    }
    let table = budget.app_base as u32;
    if !words.contains(&VTOR) || !words.contains(&table) {
        missing.push(format!("VTOR ({VTOR:#010x}) set to {table:#010x}"));
    }
    for (register, what) in [
        (NVIC_ICER0, "NVIC enables cleared"),
        (NVIC_ICPR0, "NVIC pending bits cleared"),
        (SYST_CSR, "SysTick stopped"),
    ] {
        if !words.contains(&register) {
            missing.push(what.to_string());
        }
    }
    if !insns.iter().any(|i| i.hw1 == CPSIE_I && i.hw2.is_none()) {
        missing.push("cpsie i at the end".to_string());
    }
    if missing.is_empty() {
        Ok(format!(
            "Reset calls __pre_init: cpsid i, SP = {sp:#010x}, VTOR = {table:#010x}, \
             NVIC and SysTick cleared"
        ))
    } else {
        Err(format!("__pre_init lacks: {}", missing.join(", ")))
    }
}

/// `safety`: the panic handler, every fault handler and the default
/// handler reach `onechip_safe_off` (heaters and drivers off), and the
/// watchdog is started and fed.
pub fn safety(image: &Image<'_>) -> Result<String, String> {
    let off = image.function("onechip_safe_off")?;
    let mut handlers = Vec::new();
    for (index, name) in FAULT_VECTORS {
        handlers.push((name.to_string(), image.vector(index)?));
    }
    for name in ["DefaultHandler", "rust_begin_unwind"] {
        handlers.push((name.to_string(), image.function(name)?.addr));
    }
    let unsafe_paths: Vec<String> = handlers
        .iter()
        .filter(|(_, addr)| !image.reaches(*addr, off.addr, CALL_DEPTH))
        .map(|(name, _)| name.clone())
        .collect();
    if !unsafe_paths.is_empty() {
        return Err(format!(
            "onechip_safe_off (heaters and drivers off) is never called from: {}",
            unsafe_paths.join(", ")
        ));
    }
    for name in ["onechip_watchdog_start", "onechip_watchdog_feed"] {
        image.function(name)?;
    }
    Ok(
        "panic, HardFault, NMI, MemManage, BusFault, UsageFault and DefaultHandler reach \
         onechip_safe_off; the watchdog is started and fed"
            .to_string(),
    )
}

/// `forbidden`: no linked symbol lies under a `forbidden_code` path.
pub fn forbidden(image: &Image<'_>, budget: &Budget) -> Result<String, String> {
    let linked: Vec<String> = budget
        .forbidden_code
        .iter()
        .filter_map(|path| {
            image
                .symbol_under_path(path)
                .map(|symbol| format!("`{path}` is linked ({symbol})"))
        })
        .collect();
    if linked.is_empty() {
        Ok(format!("none of {}", budget.forbidden_code.join(", ")))
    } else {
        Err(linked.join("; "))
    }
}
