//! What the firmware ELF puts in flash and RAM, its vector table, and the
//! flat binary the bootloader flashes.

use object::elf::{PT_LOAD, SHF_ALLOC};
use object::read::elf::{ElfFile32, FileHeader, ProgramHeader};
use object::{Endianness, Object, ObjectSection, ObjectSymbol, SectionFlags, SymbolKind};

use crate::thumb::{self, Insn};

/// STM32 flash is mapped here and above (up to 0x1fff_ffff).
const FLASH_REGION: std::ops::Range<u64> = 0x0800_0000..0x2000_0000;
/// On-chip SRAM (DTCM, AXI SRAM, SRAM1..4) lies in this range.
const RAM_REGION: std::ops::Range<u64> = 0x2000_0000..0x4000_0000;
/// Entries before the device interrupts in the Cortex-M vector table.
const CORE_VECTORS: u64 = 16;

/// A function of the image: its symbol's name, address (Thumb bit
/// cleared) and size.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Function {
    /// Symbol name (mangled).
    pub name: String,
    /// Address of the first instruction.
    pub addr: u64,
    /// Size in bytes (code and any literal pool).
    pub size: u64,
}

/// An allocated section (in RAM, or in the TCMs): name, address, size.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RamSection {
    /// Section name.
    pub name: String,
    /// Start address.
    pub addr: u64,
    /// Size in bytes.
    pub size: u64,
}

/// One loadable piece of the image: bytes and the flash address they go to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Segment {
    /// Load (physical) address.
    pub load_addr: u64,
    /// Contents.
    pub bytes: Vec<u8>,
}

/// A parsed firmware ELF.
pub struct Image<'a> {
    elf: ElfFile32<'a, Endianness>,
    segments: Vec<Segment>,
    /// Every allocated section that takes space, by address.
    sections: Vec<RamSection>,
    ram_sections: Vec<RamSection>,
    functions: Vec<Function>,
    /// ARM mapping symbols (`$t`: code follows, `$d`: data follows), by
    /// address: `true` for data.
    data_marks: Vec<(u64, bool)>,
}

impl<'a> Image<'a> {
    /// Parses a 32-bit little-endian ARM ELF.
    pub fn parse(data: &'a [u8]) -> Result<Self, String> {
        let elf =
            ElfFile32::<Endianness>::parse(data).map_err(|e| format!("not a 32-bit ELF: {e}"))?;
        let endian = elf.endian();
        let mut segments = Vec::new();
        for ph in elf
            .elf_header()
            .program_headers(endian, data)
            .map_err(|e| e.to_string())?
        {
            if ph.p_type(endian) != PT_LOAD || ph.p_filesz(endian) == 0 {
                continue;
            }
            let bytes = ph
                .data(endian, data)
                .map_err(|()| "segment outside the file".to_string())?;
            segments.push(Segment {
                load_addr: u64::from(ph.p_paddr(endian)),
                bytes: bytes.to_vec(),
            });
        }
        let mut sections: Vec<RamSection> = elf
            .sections()
            .filter(|s| is_allocated(s) && s.size() > 0)
            .map(|s| RamSection {
                name: s.name().unwrap_or("?").to_string(),
                addr: s.address(),
                size: s.size(),
            })
            .collect();
        sections.sort_by_key(|s| s.addr);
        let ram_sections = sections
            .iter()
            .filter(|s| RAM_REGION.contains(&s.addr))
            .cloned()
            .collect();
        let mut functions: Vec<Function> = elf
            .symbols()
            .filter(|s| s.kind() == SymbolKind::Text && s.size() > 0)
            .filter_map(|s| {
                Some(Function {
                    name: s.name().ok()?.to_string(),
                    addr: s.address() & !1,
                    size: s.size(),
                })
            })
            .collect();
        functions.sort_by_key(|f| f.addr);
        let mut data_marks: Vec<(u64, bool)> = elf
            .symbols()
            .filter_map(|s| {
                let name = s.name().ok()?;
                let data = name == "$d" || name.starts_with("$d.");
                let code = name == "$t" || name.starts_with("$t.");
                (data || code).then_some((s.address() & !1, data))
            })
            .collect();
        data_marks.sort_unstable();
        Ok(Self {
            elf,
            segments,
            sections,
            ram_sections,
            functions,
            data_marks,
        })
    }

    /// Bytes stored in flash: code, read-only data and the initial values of
    /// `.data`.
    pub fn flash_bytes(&self) -> u64 {
        self.segments
            .iter()
            .filter(|s| FLASH_REGION.contains(&s.load_addr))
            .map(|s| s.bytes.len() as u64)
            .sum()
    }

    /// Statically allocated RAM: `.data`, `.bss`, `.uninit` and the like.
    pub fn static_ram_bytes(&self) -> u64 {
        self.ram_sections.iter().map(|s| s.size).sum()
    }

    /// The sections in RAM that take space (`.data`, `.bss`, `.uninit`).
    pub fn ram_sections(&self) -> &[RamSection] {
        &self.ram_sections
    }

    /// The allocated sections that lie in `range` (a TCM), by address.
    pub fn sections_in(&self, range: &std::ops::Range<u64>) -> Vec<&RamSection> {
        self.sections
            .iter()
            .filter(|s| range.contains(&s.addr))
            .collect()
    }

    /// Where the vector table (the application) starts.
    pub fn vector_table_address(&self) -> Result<u64, String> {
        let table =
            (self.elf.section_by_name(".vector_table")).ok_or("no .vector_table section")?;
        Ok(table.address())
    }

    /// Word `index` of the vector table (0: initial stack pointer, 1:
    /// reset, 2: NMI, 3: HardFault, ...), Thumb bit included.
    pub fn vector(&self, index: u64) -> Result<u64, String> {
        let table = self
            .elf
            .section_by_name(".vector_table")
            .ok_or("no .vector_table section")?;
        let data = table.data().map_err(|e| e.to_string())?;
        let offset = (index * 4) as usize;
        let word = data
            .get(offset..offset + 4)
            .ok_or_else(|| format!("vector table has no entry {index}"))?;
        Ok(u64::from(u32::from_le_bytes([
            word[0], word[1], word[2], word[3],
        ])))
    }

    /// The function whose symbol is exactly `name`, or else the one whose
    /// name ends with `name` (a mangled `…rust_begin_unwind`).
    pub fn function(&self, name: &str) -> Result<&Function, String> {
        self.functions
            .iter()
            .find(|f| f.name == name)
            .or_else(|| self.functions.iter().find(|f| f.name.ends_with(name)))
            .ok_or_else(|| format!("function `{name}` is not in the image"))
    }

    /// The function that starts at `addr` (the Thumb bit ignored).
    pub fn function_at(&self, addr: u64) -> Option<&Function> {
        let addr = addr & !1;
        self.functions.iter().find(|f| f.addr == addr)
    }

    /// The bytes of `function`.
    pub fn code(&self, function: &Function) -> Result<&[u8], String> {
        let section = self
            .elf
            .sections()
            .filter(is_allocated)
            .find(|s| (s.address()..s.address() + s.size()).contains(&function.addr))
            .ok_or_else(|| format!("`{}` lies in no section", function.name))?;
        let data = section.data().map_err(|e| e.to_string())?;
        let start = (function.addr - section.address()) as usize;
        data.get(start..start + function.size as usize)
            .ok_or_else(|| format!("`{}` runs past its section", function.name))
    }

    /// The functions of the image, by address.
    pub fn functions(&self) -> &[Function] {
        &self.functions
    }

    /// The instructions of `function`, decoded from its start; literal
    /// pools and jump tables the ELF marks as data (`$d`) are skipped.
    pub fn instructions(&self, function: &Function) -> Result<Vec<Insn>, String> {
        let code = self.code(function)?;
        let end = function.addr + function.size;
        let mut insns = Vec::new();
        for (start, stop) in code_ranges(&self.data_marks, function.addr, end) {
            let bytes = &code[(start - function.addr) as usize..(stop - function.addr) as usize];
            insns.extend(thumb::decode(bytes, start));
        }
        Ok(insns)
    }

    /// The 32-bit words at word-aligned addresses in `function` (its
    /// literal pool among them).
    pub fn words(&self, function: &Function) -> Result<Vec<u32>, String> {
        let code = self.code(function)?;
        let skip = ((4 - function.addr % 4) % 4) as usize;
        Ok(code
            .get(skip..)
            .unwrap_or_default()
            .chunks_exact(4)
            .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
            .collect())
    }

    /// True if the function at `from` calls or jumps to `target` directly,
    /// or through functions it calls, at most `depth` calls deep.
    pub fn reaches(&self, from: u64, target: u64, depth: usize) -> bool {
        let mut seen = vec![from & !1];
        let mut frontier = vec![from & !1];
        for _ in 0..depth {
            let mut next = Vec::new();
            for addr in frontier {
                let Some(function) = self.function_at(addr) else {
                    continue;
                };
                let Ok(insns) = self.instructions(function) else {
                    continue;
                };
                for to in insns.iter().filter_map(|i| i.branch) {
                    if to == target & !1 {
                        return true;
                    }
                    // Calls into other functions only (not jumps within).
                    if self.function_at(to).is_some() && !seen.contains(&to) {
                        seen.push(to);
                        next.push(to);
                    }
                }
            }
            frontier = next;
        }
        false
    }

    /// Address of a global symbol (the Thumb bit cleared).
    pub fn symbol(&self, name: &str) -> Result<u64, String> {
        self.elf
            .symbols()
            .find(|s| s.name() == Ok(name))
            .map(|s| s.address() & !1)
            .ok_or_else(|| format!("symbol `{name}` not found in the ELF"))
    }

    /// Address and size of the symbol named exactly `name`.
    pub fn symbol_extent(&self, name: &str) -> Result<(u64, u64), String> {
        self.elf
            .symbols()
            .find(|s| s.name() == Ok(name))
            .map(|s| (s.address() & !1, s.size()))
            .ok_or_else(|| format!("symbol `{name}` not found in the ELF"))
    }

    /// True if some symbol's (mangled) name contains `fragment`.
    pub fn has_symbol_containing(&self, fragment: &str) -> bool {
        self.elf
            .symbols()
            .any(|s| s.name().is_ok_and(|n| n.contains(fragment)))
    }

    /// A symbol (mangled name) under the Rust path `path`
    /// (`embassy_stm32::adc::_version`), if any: legacy and v0 mangling
    /// write each path segment as its length and text, generic impl paths
    /// write `a..b`.
    pub fn symbol_under_path(&self, path: &str) -> Option<String> {
        let segments: Vec<&str> = path.split("::").collect();
        let mangled: String = segments.iter().map(|s| format!("{}{s}", s.len())).collect();
        let dotted = segments.join("..");
        self.elf.symbols().find_map(|s| {
            let name = s.name().ok()?;
            (name.contains(&mangled) || name.contains(&dotted)).then(|| name.to_string())
        })
    }

    /// The handler address the vector table holds for device interrupt `irq`.
    pub fn interrupt_handler(&self, irq: u64) -> Result<u64, String> {
        let table = self
            .elf
            .section_by_name(".vector_table")
            .ok_or("no .vector_table section")?;
        let data = table.data().map_err(|e| e.to_string())?;
        let offset = ((CORE_VECTORS + irq) * 4) as usize;
        let word = data
            .get(offset..offset + 4)
            .ok_or_else(|| format!("vector table has no entry for IRQ {irq}"))?;
        Ok(u64::from(u32::from_le_bytes([word[0], word[1], word[2], word[3]])) & !1)
    }

    /// The flash contents from `base` on, gaps filled with erased flash
    /// (0xff), as the bootloader expects in `firmware.bin`.
    pub fn flat_binary(&self, base: u64) -> Result<Vec<u8>, String> {
        flatten(&self.segments, base)
    }
}

/// True for a section the image occupies memory with (not debug info,
/// which the ELF places at address 0).
fn is_allocated(section: &object::read::elf::ElfSection32<'_, '_, Endianness>) -> bool {
    matches!(section.flags(), SectionFlags::Elf { sh_flags } if sh_flags & u64::from(SHF_ALLOC) != 0)
}

/// The parts of `start..end` that are code, by the mapping symbols `marks`
/// (sorted; `true` for data): a function starts with code, data runs
/// from a `$d` to the next `$t`.
fn code_ranges(marks: &[(u64, bool)], start: u64, end: u64) -> Vec<(u64, u64)> {
    let before = marks.partition_point(|&(a, _)| a <= start);
    let mut data = false;
    let mut ranges = Vec::new();
    let mut from = start;
    for &(addr, is_data) in marks[before..].iter().take_while(|(a, _)| *a < end) {
        if is_data && !data {
            ranges.push((from, addr));
        } else if !is_data && data {
            from = addr;
        }
        data = is_data;
    }
    if !data {
        ranges.push((from, end));
    }
    ranges.retain(|(a, b)| a < b);
    ranges
}

/// Lays segments out from `base`; every flash segment must lie at or above it.
pub fn flatten(segments: &[Segment], base: u64) -> Result<Vec<u8>, String> {
    let flash: Vec<&Segment> = segments
        .iter()
        .filter(|s| FLASH_REGION.contains(&s.load_addr))
        .collect();
    let first = flash
        .iter()
        .map(|s| s.load_addr)
        .min()
        .ok_or("no flash contents")?;
    if first != base {
        return Err(format!(
            "image starts at {first:#010x}, not at the bootloader's {base:#010x}"
        ));
    }
    let end = flash
        .iter()
        .map(|s| s.load_addr + s.bytes.len() as u64)
        .max()
        .unwrap_or(base);
    let mut bin = vec![0xff; (end - base) as usize];
    for s in flash {
        let at = (s.load_addr - base) as usize;
        bin[at..at + s.bytes.len()].copy_from_slice(&s.bytes);
    }
    Ok(bin)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seg(load_addr: u64, bytes: &[u8]) -> Segment {
        Segment {
            load_addr,
            bytes: bytes.to_vec(),
        }
    }

    #[test]
    fn flatten_places_segments_and_fills_gaps_with_erased_flash() {
        let segs = [
            seg(0x0802_0004, &[3, 4]),
            seg(0x0802_0000, &[1, 2]),
            seg(0x2400_0000, &[9]),
        ];
        let bin = flatten(&segs, 0x0802_0000).expect("laid out");
        assert_eq!(bin, [1, 2, 0xff, 0xff, 3, 4]);
    }

    #[test]
    fn code_ranges_skip_data_between_mapping_symbols() {
        // $t at 0x100, $d at 0x110 (a literal pool), $t at 0x118.
        let marks = [(0x100, false), (0x110, true), (0x118, false), (0x200, true)];
        assert_eq!(
            code_ranges(&marks, 0x100, 0x120),
            [(0x100, 0x110), (0x118, 0x120)]
        );
        // A function starts with code even after another's data; no
        // marks: all code.
        assert_eq!(code_ranges(&marks, 0x112, 0x116), [(0x112, 0x116)]);
        assert_eq!(code_ranges(&[], 0x10, 0x20), [(0x10, 0x20)]);
    }

    #[test]
    fn an_image_not_linked_at_the_bootloader_offset_is_refused() {
        let err = flatten(&[seg(0x0800_0000, &[1])], 0x0802_0000).expect_err("wrong base");
        assert!(err.contains("0x08000000"), "{err}");
    }
}
