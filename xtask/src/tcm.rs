//! `tcm`: the stepper interrupt runs from the tightly-coupled memories
//! and the caches are set up at boot (board-rt/src/tcm.rs, board/src/cache.rs), checked
//! on the image, as nothing else can show it without the board:
//!
//! - every function the stepper interrupt's handler reaches over direct
//!   calls (the [`Graph`] the stack estimate walks, linker thunks
//!   followed) lies in ITCM, but for `itcm_exempt` (whose callees are not
//!   followed);
//! - every `dtcm_data` static lies in DTCM, every `dma_data` static in the
//!   MPU's non-cacheable region (`__dma_region_start..__dma_region_end`);
//! - the reset handler reaches every `boot_calls` function over direct
//!   calls (the TCM load, the caches' set-up).

use std::ops::Range;

use crate::budget::Budget;
use crate::call_graph::{Graph, demangle};
use crate::elf_image::Image;

/// The rule, with the memories' use.
pub fn check(image: &Image<'_>, budget: &Budget) -> Result<String, String> {
    let graph = Graph::build(image)?;
    let itcm = budget.itcm_base..budget.itcm_base + budget.itcm_kib * 1024;
    let dtcm = budget.dtcm_base..budget.dtcm_base + budget.dtcm_kib * 1024;
    let mut problems = Vec::new();
    let mut found = Vec::new();

    let handler = image.interrupt_handler(budget.stepper_irq_number)?;
    let root = graph
        .at(handler)
        .ok_or_else(|| format!("no function at the stepper handler {handler:#010x}"))?;
    match hot_path_in_itcm(&graph, root, &itcm, &budget.itcm_exempt) {
        Ok(n) => found.push(format!(
            "{} and the {} functions it reaches in ITCM",
            demangle(&graph.names[root]),
            n - 1
        )),
        Err(e) => problems.push(e),
    }

    let dma = image
        .symbol("__dma_region_start")
        .and_then(|start| Ok(start..image.symbol("__dma_region_end")?));
    let dma = dma.unwrap_or_else(|e| {
        problems.push(format!("the non-cacheable DMA region: {e}"));
        0..0
    });
    for (paths, range, memory) in [
        (&budget.dtcm_data, &dtcm, "DTCM"),
        (&budget.dma_data, &dma, "the non-cacheable DMA region"),
    ] {
        for path in paths {
            let placed = image
                .symbol_under_path(path)
                .ok_or_else(|| format!("no static `{path}` in the image"))
                .and_then(|name| image.symbol_extent(&name))
                .and_then(|(addr, size)| lies_in(path, addr, size, range, memory));
            match placed {
                Ok(at) => found.push(at),
                Err(e) => problems.push(e),
            }
        }
    }

    let reset = graph
        .at(image.vector(1)?)
        .ok_or("the reset vector points at no function")?;
    for name in &budget.boot_calls {
        match boot_path(&graph, reset, name) {
            Ok(path) => found.push(format!("boot path {path}")),
            Err(e) => problems.push(e),
        }
    }

    let used =
        |range: &Range<u64>| -> u64 { image.sections_in(range).iter().map(|s| s.size).sum() };
    found.push(format!(
        "ITCM {} of {} bytes, DTCM {} of {} bytes",
        used(&itcm),
        itcm.end - itcm.start,
        used(&dtcm),
        dtcm.end - dtcm.start
    ));
    if problems.is_empty() {
        Ok(found.join("; "))
    } else {
        Err(problems.join("; "))
    }
}

/// Checks that every function `root` reaches lies in `itcm`, not going on
/// from functions whose names contain an `exempt` fragment (those may lie
/// anywhere). Returns how many functions lie in ITCM on the way.
fn hot_path_in_itcm(
    graph: &Graph,
    root: usize,
    itcm: &Range<u64>,
    exempt: &[String],
) -> Result<usize, String> {
    let is_exempt = |f: usize| exempt.iter().any(|x| graph.names[f].contains(x.as_str()));
    let reached = graph.reachable(root, |f| !is_exempt(f));
    let outside: Vec<String> = reached
        .iter()
        .filter(|&&f| !is_exempt(f) && !itcm.contains(&graph.addrs[f]))
        .map(|&f| format!("{} at {:#010x}", demangle(&graph.names[f]), graph.addrs[f]))
        .collect();
    if outside.is_empty() {
        Ok(reached.len() - reached.iter().filter(|&&f| is_exempt(f)).count())
    } else {
        Err(format!(
            "the stepper interrupt `{}` reaches functions outside ITCM \
             ({:#010x}..{:#010x}): {}",
            demangle(&graph.names[root]),
            itcm.start,
            itcm.end,
            outside.join(", ")
        ))
    }
}

/// Checks that the `size` bytes at `addr` (static `what`) lie within
/// `range` (`memory`).
fn lies_in(
    what: &str,
    addr: u64,
    size: u64,
    range: &Range<u64>,
    memory: &str,
) -> Result<String, String> {
    let end = addr + size;
    if range.start <= addr && end <= range.end {
        Ok(format!("{what} ({size} bytes) at {addr:#010x} in {memory}"))
    } else {
        Err(format!(
            "{what} at {addr:#010x}..{end:#010x} is not in {memory} \
             ({:#010x}..{:#010x})",
            range.start, range.end
        ))
    }
}

/// The chain of direct calls from `reset` to the function `name`, as
/// `a -> b -> name`.
fn boot_path(graph: &Graph, reset: usize, name: &str) -> Result<String, String> {
    let target = graph.named(name)?;
    let path = graph.path(reset, target).ok_or_else(|| {
        format!(
            "`{name}` is not reached from `{}` over direct calls: it is not on the boot path",
            graph.names[reset]
        )
    })?;
    let names: Vec<String> = path.iter().map(|&f| demangle(&graph.names[f])).collect();
    Ok(names.join(" -> "))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::call_graph::from_calls;

    const ITCM: Range<u64> = 0..0x1_0000;

    /// TIM5 (ITCM) calls run_on (ITCM), which calls a thunk (ITCM) to
    /// memmove (flash) and panic_fmt (flash), which calls safe_off
    /// (flash); Reset calls main, which calls the cache set-up.
    fn image_graph(run_on_at: u64) -> Graph {
        from_calls(
            &[
                ("TIM5", 0x20),
                ("run_on", run_on_at),
                ("__Thumbv7ABSLongThunk___aeabi_memmove", 0x100),
                ("__aeabi_memmove", 0x0802_1000),
                ("_RNvNtCs1_4core9panicking9panic_fmt", 0x0802_2000),
                ("onechip_safe_off", 0x0802_3000),
                ("Reset", 0x0802_0400),
                ("main", 0x0802_0500),
                ("onechip_caches_enable", 0x0802_0600),
            ],
            &[(0, 1), (1, 2), (2, 3), (1, 4), (4, 5), (6, 7), (7, 8)],
        )
    }

    fn exempt() -> Vec<String> {
        vec!["4core9panicking".into(), "memmove".into()]
    }

    #[test]
    fn a_hot_path_in_itcm_passes_with_its_exempt_callees() {
        let g = image_graph(0x200);
        // TIM5 and run_on; the thunk to memmove (its name too), memmove
        // and the panic path exempt, safe_off beyond them not followed.
        assert_eq!(hot_path_in_itcm(&g, 0, &ITCM, &exempt()), Ok(2));
    }

    #[test]
    fn a_hot_function_in_flash_fails_and_is_named() {
        let g = image_graph(0x0803_0000);
        let err = hot_path_in_itcm(&g, 0, &ITCM, &exempt()).expect_err("run_on in flash");
        assert!(err.contains("run_on at 0x08030000"), "{err}");
        // Without the exemptions, memmove and the panic path fail too.
        let err = hot_path_in_itcm(&image_graph(0x200), 0, &ITCM, &[]).expect_err("no exemptions");
        assert!(
            err.contains("__aeabi_memmove") && err.contains("onechip_safe_off"),
            "{err}"
        );
    }

    #[test]
    fn statics_must_lie_wholly_in_their_memory() {
        let dtcm = 0x2000_0000..0x2002_0000;
        assert!(lies_in("ENGINE", 0x2000_0000, 0x33f0, &dtcm, "DTCM").is_ok());
        let err = lies_in("ENGINE", 0x2401_0000, 0x33f0, &dtcm, "DTCM").expect_err("AXI SRAM");
        assert!(err.contains("ENGINE at 0x24010000..0x240133f0"), "{err}");
        // Straddling the end.
        assert!(lies_in("ENGINE", 0x2001_fff0, 0x20, &dtcm, "DTCM").is_err());
    }

    #[test]
    fn the_boot_path_must_reach_the_cache_set_up() {
        let g = image_graph(0x200);
        assert_eq!(
            boot_path(&g, 6, "onechip_caches_enable"),
            Ok("Reset -> main -> onechip_caches_enable".into())
        );
        // Reached only from an interrupt, or not linked: refused.
        let err = boot_path(&g, 6, "onechip_safe_off").expect_err("not on the boot path");
        assert!(err.contains("not on the boot path"), "{err}");
        assert!(boot_path(&g, 6, "onechip_tcm_load").is_err());
    }
}
