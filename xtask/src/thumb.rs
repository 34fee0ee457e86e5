//! Just enough Thumb-2 decoding to follow calls in the firmware image:
//! instruction lengths, and the targets of `bl` and unconditional `b`.

/// One decoded instruction: its address, its halfwords, and where it
/// branches to if it is a `bl`, `b.w` or unconditional 16-bit `b`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Insn {
    /// Address of the instruction.
    pub addr: u64,
    /// First halfword.
    pub hw1: u16,
    /// Second halfword of a 32-bit instruction.
    pub hw2: Option<u16>,
    /// Target of a direct branch (with or without link).
    pub branch: Option<u64>,
}

/// `cpsid i`.
pub const CPSID_I: u16 = 0xb672;
/// `cpsie i`.
pub const CPSIE_I: u16 = 0xb662;

/// True if `hw1` starts a 32-bit instruction.
fn is_wide(hw1: u16) -> bool {
    matches!(hw1 >> 11, 0b11101..=0b11111)
}

/// The target of a 32-bit `bl` or `b.w` (encoding T4) at `addr`.
fn wide_branch(addr: u64, hw1: u16, hw2: u16) -> Option<u64> {
    // hw1: 11110 S imm10; hw2: 1 1 J1 1 J2 imm11 (BL) or 1 0 J1 1 J2 imm11
    // (B.W); other patterns of hw2's bits 15, 14 and 12 are BLX, the
    // conditional B.W, MSR and the like.
    let bl_or_b = matches!(hw2 & 0xd000, 0xd000 | 0x9000);
    if hw1 >> 11 != 0b11110 || !bl_or_b {
        return None;
    }
    let s = u32::from(hw1 >> 10 & 1);
    let j1 = u32::from(hw2 >> 13 & 1);
    let j2 = u32::from(hw2 >> 11 & 1);
    let i1 = !(j1 ^ s) & 1;
    let i2 = !(j2 ^ s) & 1;
    let imm10 = u32::from(hw1 & 0x3ff);
    let imm11 = u32::from(hw2 & 0x7ff);
    let imm = s << 24 | i1 << 23 | i2 << 22 | imm10 << 12 | imm11 << 1;
    // Sign-extend 25 bits.
    let offset = ((imm << 7) as i32) >> 7;
    Some((addr as i64 + 4 + i64::from(offset)) as u64)
}

/// The target of a 16-bit unconditional `b` (encoding T2) at `addr`.
fn narrow_branch(addr: u64, hw1: u16) -> Option<u64> {
    if hw1 >> 11 != 0b11100 {
        return None;
    }
    let offset = ((u32::from(hw1 & 0x7ff) << 21) as i32) >> 20;
    Some((addr as i64 + 4 + i64::from(offset)) as u64)
}

/// Decodes `code` (little-endian, loaded at `base`) instruction by
/// instruction from its start. Literal data after the code decodes as
/// instructions too; callers look for specific targets only.
pub fn decode(code: &[u8], base: u64) -> Vec<Insn> {
    let halfwords: Vec<u16> = code
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect();
    let mut insns = Vec::new();
    let mut i = 0;
    while i < halfwords.len() {
        let addr = base + 2 * i as u64;
        let hw1 = halfwords[i];
        if is_wide(hw1) {
            let Some(&hw2) = halfwords.get(i + 1) else {
                break;
            };
            insns.push(Insn {
                addr,
                hw1,
                hw2: Some(hw2),
                branch: wide_branch(addr, hw1, hw2),
            });
            i += 2;
        } else {
            insns.push(Insn {
                addr,
                hw1,
                hw2: None,
                branch: narrow_branch(addr, hw1),
            });
            i += 1;
        }
    }
    insns
}

/// True for `msr msp, rN`.
pub fn is_msr_msp(insn: &Insn) -> bool {
    insn.hw1 & 0xfff0 == 0xf380 && insn.hw2 == Some(0x8808)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bytes(halfwords: &[u16]) -> Vec<u8> {
        halfwords.iter().flat_map(|h| h.to_le_bytes()).collect()
    }

    #[test]
    fn decodes_calls_and_jumps_as_objdump_does() {
        // From the firmware: 80202d0: f000 f82a  bl 8020328 <__pre_init>
        let insns = decode(&bytes(&[0xf000, 0xf82a]), 0x0802_02d0);
        assert_eq!(insns[0].branch, Some(0x0802_0328));
        // 805a230: f000 b806  b.w 805a240 <_HardFault>
        let insns = decode(&bytes(&[0xf000, 0xb806]), 0x0805_a230);
        assert_eq!(insns[0].branch, Some(0x0805_a240));
        // Backwards: 805a248: f7d5 ff36  bl 80300b8
        let insns = decode(&bytes(&[0xf7d5, 0xff36]), 0x0805_a248);
        assert_eq!(insns[0].branch, Some(0x0803_00b8));
        // 80202e0: e7fb  b.n 80202da
        let insns = decode(&bytes(&[0xe7fb]), 0x0802_02e0);
        assert_eq!(insns[0].branch, Some(0x0802_02da));
    }

    #[test]
    fn lengths_follow_the_first_halfword() {
        // cpsid i; msr MSP, r0; movs r0, #0; bx lr
        let insns = decode(&bytes(&[0xb672, 0xf380, 0x8808, 0x2000, 0x4770]), 0x100);
        let addrs: Vec<u64> = insns.iter().map(|i| i.addr).collect();
        assert_eq!(addrs, [0x100, 0x102, 0x106, 0x108]);
        assert_eq!(insns[0].hw1, CPSID_I);
        assert!(is_msr_msp(&insns[1]));
        assert!(insns.iter().all(|i| i.branch.is_none()));
    }

    #[test]
    fn other_wide_instructions_are_not_branches() {
        // msr BASEPRI, r0; str.w r3, [r0, r2, lsl #2]; bne.n (conditional)
        let insns = decode(&bytes(&[0xf380, 0x8811, 0xf840, 0x3022, 0xd1f8]), 0x200);
        assert!(insns.iter().all(|i| i.branch.is_none()), "{insns:?}");
    }
}
