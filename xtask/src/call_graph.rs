//! The firmware's call graph over direct calls and jumps (`bl`, `b.w`,
//! `b`), with each function's frame: what the stack estimate
//! ([`crate::stack_use`]) and the TCM placement rules ([`crate::tcm`])
//! walk.
//!
//! A call between flash and ITCM (further apart than a `bl` reaches) goes
//! through a linker thunk, a function of its own that jumps on through a
//! register; the graph follows it to its target ([`thumb::thunk_target`]),
//! so such calls are edges like any other. Calls through registers
//! (`blx rN`, vtables, `fn` pointers) are counted, not followed.

use std::collections::{HashMap, VecDeque};

use crate::elf_image::Image;
use crate::thumb;

/// The image's functions (by index, in address order) and their direct
/// callees.
pub struct Graph {
    /// Symbol names (mangled).
    pub names: Vec<String>,
    /// Start addresses (Thumb bit cleared).
    pub addrs: Vec<u64>,
    /// Stack each function's code claims, bytes.
    pub frames: Vec<u64>,
    /// Each function's direct callees (sorted, without repeats).
    pub callees: Vec<Vec<usize>>,
    /// `blx rN` in the image: calls the graph does not follow.
    pub indirect_calls: usize,
    /// `sub sp, rN` of unknown amount (dynamic allocations).
    pub dynamic_frames: usize,
    by_addr: HashMap<u64, usize>,
}

impl Graph {
    /// Decodes every function of `image`.
    pub fn build(image: &Image<'_>) -> Result<Self, String> {
        let functions = image.functions();
        let mut graph = Self::new(functions.iter().map(|f| (f.name.clone(), f.addr)));
        for (i, function) in functions.iter().enumerate() {
            let insns = image.instructions(function)?;
            let frame = thumb::frame(&insns);
            graph.frames[i] = frame.bytes;
            graph.dynamic_frames += frame.dynamic;
            graph.indirect_calls += insns.iter().filter(|i| thumb::is_indirect_call(i)).count();
            let callees: Vec<usize> = match thumb::thunk_target(&insns) {
                Some(target) => graph.at(target).into_iter().collect(),
                None => insns
                    .iter()
                    .filter_map(|insn| {
                        let callee = graph.at(insn.branch?)?;
                        // A jump back to the function's own start is a loop.
                        (callee != i || thumb::is_call(insn)).then_some(callee)
                    })
                    .collect(),
            };
            graph.set_callees(i, callees);
        }
        Ok(graph)
    }

    /// Functions `(name, address)` without calls or frames yet.
    fn new(functions: impl Iterator<Item = (String, u64)>) -> Self {
        let (names, addrs): (Vec<String>, Vec<u64>) = functions.unzip();
        let n = names.len();
        Self {
            by_addr: addrs.iter().enumerate().map(|(i, &a)| (a, i)).collect(),
            names,
            addrs,
            frames: vec![0; n],
            callees: vec![Vec::new(); n],
            indirect_calls: 0,
            dynamic_frames: 0,
        }
    }

    fn set_callees(&mut self, f: usize, mut callees: Vec<usize>) {
        callees.sort_unstable();
        callees.dedup();
        self.callees[f] = callees;
    }

    /// The function starting at `addr` (the Thumb bit ignored).
    pub fn at(&self, addr: u64) -> Option<usize> {
        self.by_addr.get(&(addr & !1)).copied()
    }

    /// The function whose symbol is exactly `name`.
    pub fn named(&self, name: &str) -> Result<usize, String> {
        self.names
            .iter()
            .position(|n| n == name)
            .ok_or_else(|| format!("function `{name}` is not in the image"))
    }

    /// Every function reached from `root` over direct calls and jumps
    /// (`root` first), not going on from those `descend` refuses (they are
    /// listed, their callees not).
    pub fn reachable(&self, root: usize, descend: impl Fn(usize) -> bool) -> Vec<usize> {
        let mut seen = vec![false; self.names.len()];
        let mut order = vec![root];
        seen[root] = true;
        let mut next = 0;
        while let Some(&f) = order.get(next) {
            next += 1;
            if f != root && !descend(f) {
                continue;
            }
            for &callee in &self.callees[f] {
                if !std::mem::replace(&mut seen[callee], true) {
                    order.push(callee);
                }
            }
        }
        order
    }

    /// A shortest chain of direct calls from `from` to `to` (both
    /// included), if there is one.
    pub fn path(&self, from: usize, to: usize) -> Option<Vec<usize>> {
        let mut parent: Vec<Option<usize>> = vec![None; self.names.len()];
        let mut queue = VecDeque::from([from]);
        let mut seen = vec![false; self.names.len()];
        seen[from] = true;
        while let Some(f) = queue.pop_front() {
            if f == to {
                let mut path = vec![to];
                while let Some(p) = parent[*path.last()?] {
                    path.push(p);
                }
                path.reverse();
                return Some(path);
            }
            for &callee in &self.callees[f] {
                if !std::mem::replace(&mut seen[callee], true) {
                    parent[callee] = Some(f);
                    queue.push_back(callee);
                }
            }
        }
        None
    }
}

/// A readable form of a legacy-mangled Rust name (`_ZN4core3fmt5write17h…E`
/// to `core::fmt::write`); other names are returned as they are.
pub fn demangle(name: &str) -> String {
    let Some(mut rest) = name.strip_prefix("_ZN") else {
        return name.to_string();
    };
    let mut segments = Vec::new();
    while let Some(len_end) = rest.find(|c: char| !c.is_ascii_digit()) {
        let Ok(len) = rest[..len_end].parse::<usize>() else {
            break;
        };
        let Some(segment) = rest.get(len_end..len_end + len) else {
            break;
        };
        // A leading `$` is escaped as `_$`.
        segments.push(if segment.starts_with("_$") {
            &segment[1..]
        } else {
            segment
        });
        rest = &rest[len_end + len..];
    }
    if segments
        .last()
        .is_some_and(|s| s.len() == 17 && s.starts_with('h'))
    {
        segments.pop();
    }
    let mut text = segments.join("::");
    for (from, to) in [
        ("$LT$", "<"),
        ("$GT$", ">"),
        ("$RF$", "&"),
        ("$BP$", "*"),
        ("$C$", ","),
        ("$u20$", " "),
        ("$u7b$", "{"),
        ("$u7d$", "}"),
        ("$u5b$", "["),
        ("$u5d$", "]"),
        ("..", "::"),
    ] {
        text = text.replace(from, to);
    }
    text
}

/// A graph of the named functions at the given addresses with the given
/// calls `(caller, callee)`, by position in `functions`: for tests of the
/// rules that walk it.
#[cfg(test)]
pub fn from_calls(functions: &[(&str, u64)], calls: &[(usize, usize)]) -> Graph {
    let mut graph = Graph::new(functions.iter().map(|&(n, a)| (n.to_string(), a)));
    for f in 0..functions.len() {
        let callees = calls.iter().filter(|c| c.0 == f).map(|c| c.1).collect();
        graph.set_callees(f, callees);
    }
    graph
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn walks_stop_where_told_and_paths_are_shortest() {
        // 0 -> 1 -> 2 -> 3, 0 -> 3, 4 unreached.
        let g = from_calls(
            &[
                ("a", 0x10),
                ("b", 0x20),
                ("c", 0x30),
                ("d", 0x40),
                ("e", 0x50),
            ],
            &[(0, 1), (1, 2), (2, 3), (0, 3)],
        );
        let mut all = g.reachable(0, |_| true);
        all.sort_unstable();
        assert_eq!(all, [0, 1, 2, 3]);
        // Not going on from b: c is not reached (d is, from a).
        let mut cut = g.reachable(0, |f| f != 1);
        cut.sort_unstable();
        assert_eq!(cut, [0, 1, 3]);
        assert_eq!(g.path(0, 3), Some(vec![0, 3]));
        assert_eq!(g.path(1, 3), Some(vec![1, 2, 3]));
        assert_eq!(g.path(0, 4), None);
        assert_eq!(g.at(0x21), Some(1));
        assert_eq!(g.named("e"), Ok(4));
    }

    #[test]
    fn demangles_legacy_rust_names() {
        assert_eq!(
            demangle("_ZN4core3fmt5write17h0123456789abcdefE"),
            "core::fmt::write"
        );
        assert_eq!(
            demangle(
                "_ZN55_$LT$onechip_board..Foo$u20$as$u20$core..fmt..Debug$GT$3fmt17h0123456789abcdefE"
            ),
            "<onechip_board::Foo as core::fmt::Debug>::fmt"
        );
        assert_eq!(demangle("TIM5"), "TIM5");
    }
}
