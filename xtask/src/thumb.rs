//! Just enough Thumb-2 decoding to follow calls in the firmware image:
//! instruction lengths, the targets of `bl` and unconditional `b`, and
//! the stack a function's prologue claims.

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

/// True for a `bl` (a direct call, as against a `b` or `b.w` jump).
pub fn is_call(insn: &Insn) -> bool {
    insn.branch.is_some() && insn.hw2.is_some_and(|h| h & 0x4000 != 0)
}

/// True for `blx rN`, a call through a register.
pub fn is_indirect_call(insn: &Insn) -> bool {
    insn.hw2.is_none() && insn.hw1 & 0xff87 == 0x4780
}

/// `bx ip`, and the first halfwords of `movw` and `movt` (less their
/// immediate and register bits).
const BX_IP: u16 = 0x4760;
const MOVW: u16 = 0xf240;
const MOVT: u16 = 0xf2c0;

/// The target of a linker's long-branch thunk (lld's
/// `__Thumbv7ABSLongThunk_*`, which a `bl` too far for its range goes
/// through, as between flash and ITCM): `insns` are exactly `movw ip, #lo;
/// movt ip, #hi; bx ip`. The Thumb bit is cleared.
pub fn thunk_target(insns: &[Insn]) -> Option<u64> {
    const IP: usize = 12;
    let [movw, movt, bx] = insns else {
        return None;
    };
    let is_op = |insn: &Insn, op: u16| insn.hw1 & 0xfbf0 == op;
    if !is_op(movw, MOVW) || !is_op(movt, MOVT) || bx.hw1 != BX_IP || bx.hw2.is_some() {
        return None;
    }
    let mut consts = [None; 16];
    let (_, low) = mov_constant(movw, &consts).filter(|&(r, _)| r == IP)?;
    consts[IP] = Some(low);
    let (_, target) = mov_constant(movt, &consts).filter(|&(r, _)| r == IP)?;
    Some(u64::from(target & !1))
}

/// The stack a function's code claims: the sum of every `push`, `vpush`,
/// `str rN, [sp, #-n]!` and `sub sp` in it (a bound on its frame, as
/// LLVM writes one prologue and releases it on every exit).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Frame {
    /// Bytes pushed or subtracted from SP.
    pub bytes: u64,
    /// `sub sp, rN` whose amount is not a `movw`/`movt` constant (a
    /// dynamic allocation, not counted in `bytes`).
    pub dynamic: usize,
}

/// Adds up the stack `insns` (one function's code) claim.
pub fn frame(insns: &[Insn]) -> Frame {
    let mut frame = Frame::default();
    // Constants loaded by `movw`/`movt`, by register, for `sub sp, rN`.
    let mut consts = [None::<u32>; 16];
    for insn in insns {
        if let Some((reg, value)) = mov_constant(insn, &consts) {
            consts[reg] = Some(value);
            continue;
        }
        match stack_claim(insn) {
            Some(Claim::Bytes(n)) => frame.bytes += u64::from(n),
            Some(Claim::Register(r)) => match consts[r] {
                Some(n) => frame.bytes += u64::from(n),
                None => frame.dynamic += 1,
            },
            None => {}
        }
    }
    frame
}

/// What one instruction takes from the stack.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Claim {
    /// A known number of bytes.
    Bytes(u32),
    /// `sub sp, sp, rN`: the value of register N.
    Register(usize),
}

/// The stack `insn` claims, if it pushes or subtracts from SP.
fn stack_claim(insn: &Insn) -> Option<Claim> {
    let hw1 = insn.hw1;
    let Some(hw2) = insn.hw2 else {
        return match hw1 {
            // push {rlist} (T1): 1011 010 M rlist.
            _ if hw1 & 0xfe00 == 0xb400 => Some(Claim::Bytes(4 * (hw1 & 0x1ff).count_ones())),
            // sub sp, #imm7 << 2 (T1): 1011 0000 1 imm7.
            _ if hw1 & 0xff80 == 0xb080 => Some(Claim::Bytes(u32::from(hw1 & 0x7f) << 2)),
            _ => None,
        };
    };
    let rd_is_sp = hw2 & 0x8f00 == 0x0d00;
    match hw1 {
        // push.w / stmdb sp!, {rlist} (T2).
        0xe92d => Some(Claim::Bytes(4 * u32::from(hw2).count_ones())),
        // str.w rt, [sp, #-imm8]! (T4: P=1 U=0 W=1).
        0xf84d if hw2 & 0x0f00 == 0x0d00 => Some(Claim::Bytes(u32::from(hw2 & 0xff))),
        // vpush {dN..} / {sN..} (imm8 counts words either way).
        _ if hw1 & 0xffbf == 0xed2d && hw2 & 0x0e00 == 0x0a00 => {
            Some(Claim::Bytes(4 * u32::from(hw2 & 0xff)))
        }
        // sub.w sp, sp, #const (T2, S=0).
        _ if hw1 & 0xfbff == 0xf1ad && rd_is_sp => Some(Claim::Bytes(thumb_expand_imm(
            u32::from(hw1 >> 10 & 1) << 11 | u32::from(hw2 >> 4 & 0x700) | u32::from(hw2 & 0xff),
        ))),
        // subw sp, sp, #imm12 (T3).
        _ if hw1 & 0xfbff == 0xf2ad && rd_is_sp => Some(Claim::Bytes(
            u32::from(hw1 >> 10 & 1) << 11 | u32::from(hw2 >> 4 & 0x700) | u32::from(hw2 & 0xff),
        )),
        // sub.w sp, sp, rM (T1, S=0, no shift).
        0xebad if rd_is_sp && hw2 & 0x70f0 == 0 => Some(Claim::Register(usize::from(hw2 & 0xf))),
        _ => None,
    }
}

/// `movw rD, #imm16` or `movt rD, #imm16`: the register and its value
/// after it (`movt` keeps the low half `consts` knows).
fn mov_constant(insn: &Insn, consts: &[Option<u32>; 16]) -> Option<(usize, u32)> {
    let hw2 = insn.hw2?;
    let top = insn.hw1 & 0xfbf0;
    if (top != MOVW && top != MOVT) || hw2 & 0x8000 != 0 {
        return None;
    }
    let imm16 = u32::from(insn.hw1 & 0xf) << 12
        | u32::from(insn.hw1 >> 10 & 1) << 11
        | u32::from(hw2 >> 4 & 0x700)
        | u32::from(hw2 & 0xff);
    let rd = usize::from(hw2 >> 8 & 0xf);
    if top == MOVW {
        Some((rd, imm16))
    } else {
        Some((rd, imm16 << 16 | consts[rd].unwrap_or(0) & 0xffff))
    }
}

/// ThumbExpandImm of a 12-bit `i:imm3:imm8` (ARMv7-M ARM A5.3.2).
fn thumb_expand_imm(imm12: u32) -> u32 {
    let imm8 = imm12 & 0xff;
    match imm12 >> 8 {
        0 => imm8,
        1 => imm8 << 16 | imm8,
        2 => imm8 << 24 | imm8 << 8,
        3 => imm8 << 24 | imm8 << 16 | imm8 << 8 | imm8,
        _ => (0x80 | imm12 & 0x7f).rotate_right(imm12 >> 7),
    }
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

    /// The stack the instructions `halfwords` claim.
    fn frame_of(halfwords: &[u16]) -> Frame {
        frame(&decode(&bytes(halfwords), 0x1000))
    }

    #[test]
    fn prologues_add_up_as_objdump_shows_them() {
        // From the firmware's load_printer closure:
        // push {r4, r5, r6, r7, lr}; add r7, sp, #12;
        // stmdb sp!, {r8, r9, sl, fp}; sub sp, #4; vpush {d8-d15};
        // sub.w sp, sp, #157696; sub.w sp, sp, #728
        let f = frame_of(&[
            0xb5f0, 0xaf03, 0xe92d, 0x0f00, 0xb081, 0xed2d, 0x8b10, 0xf5ad, 0x3d1a, 0xf5ad, 0x7d36,
        ]);
        assert_eq!(f.bytes, 20 + 16 + 4 + 64 + 157_696 + 728);
        assert_eq!(f.dynamic, 0);
        // push {r7, lr}; str.w r8, [sp, #-4]!; vpush {d8}; sub sp, #0x1fc
        let f = frame_of(&[0xb580, 0xf84d, 0x8d04, 0xed2d, 0x8b02, 0xb0ff]);
        assert_eq!(f.bytes, 8 + 4 + 8 + 0x1fc);
        // subw sp, sp, #0x674 (T3); sub.w sp, sp, #0x214 (T2, rotated)
        assert_eq!(frame_of(&[0xf2ad, 0x6d74]).bytes, 0x674);
        assert_eq!(frame_of(&[0xf5ad, 0x7d05]).bytes, 0x214);
        // vpush {s16-s17} (single precision: 2 words)
        assert_eq!(frame_of(&[0xed2d, 0x8a02]).bytes, 8);
    }

    #[test]
    fn large_frames_from_movw_movt_and_dynamic_ones() {
        // movw ip, #0x2345; movt ip, #0x1; sub.w sp, sp, ip
        let f = frame_of(&[0xf242, 0x3c45, 0xf2c0, 0x0c01, 0xebad, 0x0d0c]);
        assert_eq!((f.bytes, f.dynamic), (0x1_2345, 0));
        // sub.w sp, sp, r0 with r0 unknown: a dynamic allocation.
        let f = frame_of(&[0xebad, 0x0d00]);
        assert_eq!((f.bytes, f.dynamic), (0, 1));
    }

    #[test]
    fn releasing_and_other_instructions_claim_nothing() {
        // add sp, #8; pop {r4, pc}; add.w sp, sp, #0x214; vpop {d8-d15};
        // ldmia.w sp!, {r8, r9, sl, fp}; sub r0, sp, #4 (not SP's own);
        // str.w r0, [sp, #4] (no writeback).
        let f = frame_of(&[
            0xb002, 0xbd10, 0xf50d, 0x7d05, 0xecbd, 0x8b10, 0xe8bd, 0x0f00, 0xf1ad, 0x0004, 0xf8cd,
            0x0004,
        ]);
        assert_eq!(f, Frame::default());
    }

    #[test]
    fn calls_and_indirect_calls_are_told_apart() {
        // bl; b.w; blx r3; bx lr
        let insns = decode(
            &bytes(&[0xf000, 0xf82a, 0xf000, 0xb806, 0x4798, 0x4770]),
            0x100,
        );
        assert!(is_call(&insns[0]) && !is_call(&insns[1]));
        assert!(is_indirect_call(&insns[2]) && !is_indirect_call(&insns[3]));
    }

    #[test]
    fn long_branch_thunks_lead_to_their_target() {
        // From the firmware: __Thumbv7ABSLongThunk___aeabi_memmove at
        // 0x115c (ITCM): movw ip, #0x23c9; movt ip, #0x806; bx ip.
        let thunk = decode(&bytes(&[0xf242, 0x3cc9, 0xf6c0, 0x0c06, 0x4760]), 0x115c);
        assert_eq!(thunk_target(&thunk), Some(0x0806_23c8));
        // Another register, or a return instead of the jump: no thunk.
        let r0 = decode(&bytes(&[0xf242, 0x30c9, 0xf6c0, 0x0006, 0x4700]), 0x115c);
        assert_eq!(thunk_target(&r0), None);
        let ret = decode(&bytes(&[0xf242, 0x3cc9, 0xf6c0, 0x0c06, 0x4770]), 0x115c);
        assert_eq!(thunk_target(&ret), None);
    }

    #[test]
    fn other_wide_instructions_are_not_branches() {
        // msr BASEPRI, r0; str.w r3, [r0, r2, lsl #2]; bne.n (conditional)
        let insns = decode(&bytes(&[0xf380, 0x8811, 0xf840, 0x3022, 0xd1f8]), 0x200);
        assert!(insns.iter().all(|i| i.branch.is_none()), "{insns:?}");
    }
}
