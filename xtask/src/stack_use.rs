//! `stack use`: a static estimate of the firmware's worst-case stack, from
//! the ELF.
//!
//! Each function's frame is what its code pushes and subtracts from SP
//! ([`crate::thumb::frame`]); its depth is its frame plus the deepest of
//! the functions it calls or jumps to directly (`bl`, `b.w`, `b`: a tail
//! call counts as a call, keeping the caller's frame; the [`Graph`]
//! follows linker thunks between flash and ITCM). Thread mode's figure is
//! the deepest function of the image that is not an exception handler:
//! embassy polls task futures through function pointers, so every
//! function counts as a root rather than only `Reset`'s tree. Interrupts
//! add, for each priority level of `irq_priorities` and for the faults
//! above them, the deepest handler of that level and its exception frame.
//! Calls through registers (`blx rN`, vtables, `fn` pointers) are not
//! followed; a recursion is counted as one pass through its cycle.

use std::collections::{BTreeMap, HashMap};

use crate::budget::Budget;
use crate::call_graph::{Graph, demangle};
use crate::elf_image::Image;

/// An exception frame with the FPU's state (26 words: the firmware is
/// hard-float, so any interrupted code may have live FP registers), plus
/// the word of padding that keeps SP 8-byte aligned.
const EXCEPTION_FRAME: u64 = 27 * 4;
/// Vector table entries of the faults and NMI, which preempt every
/// interrupt (2: NMI .. 6: UsageFault).
const FAULTS: std::ops::RangeInclusive<u64> = 2..=6;
/// First vector table entry that may hold a configurable-priority
/// handler (11: SVCall; 12 and 13 are reserved, 14: PendSV, 15: SysTick,
/// then the device interrupts).
const FIRST_CONFIGURABLE: u64 = 11;

/// Each function's deepest direct-call path, found depth-first.
struct Depths<'g> {
    graph: &'g Graph,
    /// Stack bytes from entering the function to the end of its deepest
    /// path, once known.
    depth: Vec<Option<u64>>,
    /// The callee the deepest path goes on to.
    next: Vec<Option<usize>>,
    on_path: Vec<bool>,
    /// Calls that close a cycle (caller, callee): recursion.
    cycles: Vec<(usize, usize)>,
}

impl<'g> Depths<'g> {
    fn new(graph: &'g Graph) -> Self {
        let n = graph.names.len();
        Self {
            graph,
            depth: vec![None; n],
            next: vec![None; n],
            on_path: vec![false; n],
            cycles: Vec::new(),
        }
    }

    fn of(&mut self, f: usize) -> u64 {
        if let Some(d) = self.depth[f] {
            return d;
        }
        self.on_path[f] = true;
        let mut deepest = (0, None);
        for &callee in &self.graph.callees[f] {
            if self.on_path[callee] {
                // Recursion: the cycle counts once.
                self.cycles.push((f, callee));
                continue;
            }
            let d = self.of(callee);
            if d > deepest.0 {
                deepest = (d, Some(callee));
            }
        }
        self.on_path[f] = false;
        let d = self.graph.frames[f] + deepest.0;
        self.depth[f] = Some(d);
        self.next[f] = deepest.1;
        d
    }

    /// The deepest path from `f`: each function's (demangled) name and
    /// frame in bytes.
    fn path(&mut self, f: usize) -> Vec<String> {
        self.of(f);
        let mut path = Vec::new();
        let mut at = Some(f);
        while let Some(g) = at {
            path.push(format!(
                "{} ({})",
                demangle(&self.graph.names[g]),
                self.graph.frames[g]
            ));
            at = self.next[g];
        }
        path
    }
}

/// `stack use`: the worst case of thread mode plus one handler of each
/// interrupt priority level (and the faults) nested on it, over direct
/// calls, must leave `stack_margin_kib` of the `stack_kib` stack.
pub fn check(image: &Image<'_>, budget: &Budget) -> Result<String, String> {
    let graph = Graph::build(image)?;
    let index: HashMap<&str, usize> = graph
        .names
        .iter()
        .enumerate()
        .map(|(i, n)| (n.as_str(), i))
        .collect();
    let handler_at = |addr: u64| {
        image
            .function_at(addr)
            .and_then(|f| index.get(f.name.as_str()).copied())
    };
    let default = handler_at(image.function("DefaultHandler")?.addr);

    // Handlers with configurable priorities must all be in the budget.
    let mut handlers: Vec<usize> = Vec::new();
    let mut unlisted = Vec::new();
    for entry in FIRST_CONFIGURABLE.. {
        let Ok(vector) = image.vector(entry) else {
            break;
        };
        let Some(h) = handler_at(vector) else {
            continue;
        };
        handlers.push(h);
        let name = &graph.names[h];
        if Some(h) != default && !budget.irq_priorities.iter().any(|(n, _)| n == name) {
            unlisted.push(name.clone());
        }
    }
    if !unlisted.is_empty() {
        return Err(format!(
            "interrupt handlers without a priority in irq_priorities: {}",
            unlisted.join(", ")
        ));
    }
    let mut levels: BTreeMap<String, Vec<usize>> = BTreeMap::new();
    for (name, level) in &budget.irq_priorities {
        let h = *index
            .get(name.as_str())
            .ok_or_else(|| format!("irq_priorities: no handler `{name}` in the image"))?;
        levels.entry(format!("P{level}")).or_default().push(h);
    }
    for entry in FAULTS {
        if let Some(h) = handler_at(image.vector(entry)?) {
            handlers.push(h);
            levels.entry("faults".into()).or_default().push(h);
        }
    }

    let mut depths = Depths::new(&graph);
    let thread_root = (0..graph.names.len())
        .filter(|f| !handlers.contains(f))
        .max_by_key(|&f| depths.of(f))
        .ok_or("the image has no functions")?;
    let thread = depths.of(thread_root);
    let mut interrupts = 0;
    let mut per_level = Vec::new();
    for (level, hs) in &levels {
        let (h, d) = hs
            .iter()
            .map(|&h| (h, depths.of(h) + EXCEPTION_FRAME))
            .max_by_key(|&(_, d)| d)
            .unwrap_or_default();
        interrupts += d;
        per_level.push(format!("{level} {} {d}", graph.names[h]));
    }
    let total = thread + interrupts;
    let path = depths.path(thread_root);
    let mut cycles: Vec<String> = depths
        .cycles
        .iter()
        .map(|&(a, b)| {
            format!(
                "{} -> {}",
                demangle(&graph.names[a]),
                demangle(&graph.names[b])
            )
        })
        .collect();
    cycles.sort_unstable();
    cycles.dedup();

    let stack = budget.stack_kib * 1024;
    let limit = stack.saturating_sub(budget.stack_margin_kib * 1024);
    let found = format!(
        "~{:.1} KiB worst case over direct calls (thread {thread} + interrupts {interrupts} \
         bytes: {}; exception frames {EXCEPTION_FRAME} bytes each), of {} KiB; deepest path: \
         {}; not followed: {} indirect calls (blx), {} dynamic frames; recursion counted once: \
         {}",
        total as f64 / 1024.0,
        per_level.join(", "),
        budget.stack_kib,
        path.join(" -> "),
        graph.indirect_calls,
        graph.dynamic_frames,
        if cycles.is_empty() {
            "none".to_string()
        } else {
            format!("{} ({})", cycles.len(), cycles.join(", "))
        },
    );
    let over = format!(
        "more than the stack less its {} KiB margin",
        budget.stack_margin_kib
    );
    if total > limit {
        Err(format!("{found}: {over}"))
    } else {
        Ok(found)
    }
}
