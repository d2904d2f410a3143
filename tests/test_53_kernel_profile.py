"""lgshape.bench.kernel_profile's attribution of samples to a kernel's loops.

Oracle: hand-assembled x86-64 machine code whose loops are known by
construction (a backward ``jne`` closes an inner loop, a backward ``jmp``
an outer one), with samples placed on chosen instructions, so every share
is a count divided by the total. Needs ``objdump``; ``perf`` is not run.
"""
import collections
import shutil

import pytest

pytestmark = pytest.mark.skipif(shutil.which("objdump") is None, reason="needs objdump")

BASE = 0x7F0000001000


@pytest.fixture(scope="module")
def kp():
    from lgshape.bench import kernel_profile
    return kernel_profile


# offset: instruction
#  0: nop                       (before the loops)
#  1: nop                       <- outer loop starts
#  2: nop                       <- inner loop starts
#  3: nop
#  4: jne 2      (75 fc)        inner loop: 2..4
#  6: nop
#  7: jmp 1      (eb f8)        outer loop: 1..7
#  9: ret
CODE = bytes([0x90, 0x90, 0x90, 0x90, 0x75, 0xFC, 0x90, 0xEB, 0xF8, 0xC3])


def test01_loops_and_their_shares(kp):
    """Samples: 1 before the loops, 6 in the inner loop (3 + 2 on two
    instructions, 1 on its closing jne), 2 in the outer loop outside the
    inner one (1 on its closing jmp), 1 at the return; 2 samples outside
    the code are not counted. A loop's share includes its closing jump."""
    samples = collections.Counter({BASE + 0: 1, BASE + 2: 3, BASE + 3: 2, BASE + 4: 1,
                                   BASE + 6: 1, BASE + 7: 1, BASE + 9: 1, BASE + 100: 2})
    inside, loops, stretches, ins = kp.analyse(samples, CODE, BASE)
    assert inside == 10
    assert [a for a, _ in ins] == [0, 1, 2, 3, 4, 6, 7, 9]
    assert [(lo, hi) for lo, hi, _ in loops] == [(2, 4), (1, 7)]
    assert [sh for _, _, sh in loops] == pytest.approx([60.0, 80.0])
    got = {(lo, hi): (sh, len(part)) for lo, hi, sh, part in stretches}
    # boundaries: 0, 1, 2, 5 and 8 (a closing jump's first byte + 1), 10
    assert got == {(0, 1): (pytest.approx(10.0), 1), (1, 2): (pytest.approx(0.0), 1),
                   (2, 5): (pytest.approx(60.0), 3), (5, 8): (pytest.approx(20.0), 2),
                   (8, 10): (pytest.approx(10.0), 1)}


def test02_forward_jumps_close_no_loop(kp):
    """A forward jump (jne +2 over two nops) is a branch, not a loop."""
    code = bytes([0x75, 0x02, 0x90, 0x90, 0xC3])
    inside, loops, stretches, _ = kp.analyse(collections.Counter({BASE + 2: 4}), code, BASE)
    assert inside == 4 and loops == []
    assert [(lo, hi, sh) for lo, hi, sh, _ in stretches] == [(0, 5, pytest.approx(100.0))]


def test03_long_instructions_are_one_instruction(kp):
    """An 11-byte AVX-512 gather (objdump writes its bytes past the 7th on a
    line of their own unless told the width) inside a loop: one instruction,
    counted once, and the loop's share holds its samples."""
    gather = [0x62, 0xF2, 0xFD, 0x49, 0x92, 0x84, 0xC8, 0x00, 0x01, 0x00, 0x00]
    # 0: vgatherdpd 0x100(%rax,%ymm1,8),%zmm0{%k1} (11 bytes); 11: jne 0 (75 f3); 13: ret
    code = bytes(gather + [0x75, 0xF3, 0xC3])
    samples = collections.Counter({BASE + 11: 5, BASE + 13: 5})
    inside, loops, stretches, ins = kp.analyse(samples, code, BASE)
    assert [a for a, _ in ins] == [0, 11, 13]
    assert "gather" in ins[0][1]
    assert [(lo, hi) for lo, hi, _ in loops] == [(0, 11)]
    assert loops[0][2] == pytest.approx(50.0)
    # (a loop ends at its jump's first byte + 1: samples land on instructions' starts)
    assert [(lo, hi, len(part)) for lo, hi, _, part in stretches] == [(0, 12, 2), (12, 14, 1)]


def test04_float_instruction_counts(kp):
    """The pd / ps counts take floating-point mnemonics only, not the integer
    vp... ones whose names end the same way."""
    part = ["vaddpd %zmm1,%zmm2,%zmm3", "vfmadd213ps %zmm1,%zmm2,%zmm3",
            "vpcmpd $0x1,%zmm1,%zmm2,%k1", "vmovupd %zmm5,0x40(%rsp)", "vminps %zmm1,%zmm2,%zmm3",
            "vpgatherdd (%rbx,%zmm10,4),%zmm12{%k6}"]
    assert kp._fp_ops(part, "pd") == 2 and kp._fp_ops(part, "ps") == 2


def test05_jumps_out_of_the_code_close_no_loop(kp):
    """A backward jmp (rel32) to before the code's start, as at the edge of a
    dumped mapping, is not a loop: its target is outside the code."""
    code = bytes([0x90, 0xE9, 0x00, 0xFF, 0xFF, 0xFF, 0xC3])    # 1: jmp -256 past its end
    inside, loops, stretches, ins = kp.analyse(collections.Counter({BASE + 0: 1, BASE + 1: 1}),
                                                code, BASE)
    assert [a for a, _ in ins] == [0, 1, 6]
    assert inside == 2 and loops == []
    assert [(lo, hi) for lo, hi, _, _ in stretches] == [(0, 7)]
