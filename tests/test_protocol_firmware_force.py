"""The host names the step the Hapkit firmware applies, bit for bit (issue 19).

The firmware (``firmware_protocol/firmware/hapkit/main.c``, ``on_config`` and
``take_force``) computes the PWM step in binary32: ``n = (uint16_t)(|x| * c + 0.5f)``,
capped at ``floor(limit * c)``, with ``x`` the FORCE's binary64 rounded to binary32 by
``hp_f32_bits_from_b64``. :func:`hapsim.applied.firmware_force` must name the same step for
every force, half-steps included, where the binary64 nearest multiple (ties to even) names
another. The reference here is that C, compiled by the system C compiler with the
project's own ``hproto.c`` (binary32 arithmetic on x86-64 and arm64: SSE / FP registers,
``FLT_EVAL_METHOD`` 0; ``-ffp-contract=off``: no fused multiply-add, as on the AVR), the
constant ``c = (float)(HK_PWM_STEPS / HK_FORCE_MAX_N)`` evaluated in binary32, as avr-gcc's
32-bit ``double`` does.
"""

from __future__ import annotations

import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

import firmware_protocol as fp
from hapsim.applied import account_from_force_seq, firmware_force

CDIR = Path(fp.__file__).resolve().parent / "c"
CC = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")

pytestmark = [pytest.mark.skipif(CC is None, reason="no C compiler (cc/gcc/clang) on PATH"),
              pytest.mark.xdist_group("test_protocol_firmware_force")]

# take_force's and on_config's arithmetic, transcribed from main.c (HK_PWM_STEPS = 256);
# stdin: "xhi xlo scalebits limhi limlo" per line (hex), stdout: "n dir" per line
HELPER = r"""
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include "hproto.h"

#define HK_PWM_STEPS 256

static float float_of_f64(hp_b64_t d)
{
    uint32_t b = hp_f32_bits_from_b64(d);
    float x;
    memcpy(&x, &b, sizeof x);
    return x;
}

int main(void)
{
    unsigned long xhi, xlo, sb, lhi, llo;
    while (scanf("%lx %lx %lx %lx %lx", &xhi, &xlo, &sb, &lhi, &llo) == 5) {
        hp_b64_t xd, ld;
        float scale, fmax, c, limit, x, ax, lim_f, fl;
        uint32_t sbits = (uint32_t)sb, xb, axb, lim_bits, floor_bits;
        uint16_t lim_n, n;
        unsigned dir;
        xd.hi = (uint32_t)xhi; xd.lo = (uint32_t)xlo;
        ld.hi = (uint32_t)lhi; ld.lo = (uint32_t)llo;
        memcpy(&scale, &sbits, sizeof scale);
        fmax = scale * (float)HK_PWM_STEPS;          /* HK_FORCE_MAX_N, binary32 */
        c = (float)HK_PWM_STEPS / fmax;              /* (float)(HK_PWM_STEPS / HK_FORCE_MAX_N) */
        /* on_config */
        limit = float_of_f64(ld);
        if (limit > fmax) {
            limit = fmax;
        }
        lim_f = limit * c;
        lim_n = (uint16_t)lim_f;
        if (lim_n > HK_PWM_STEPS) {
            lim_n = HK_PWM_STEPS;
        }
        fl = (float)lim_n;
        memcpy(&floor_bits, &fl, sizeof fl);
        memcpy(&lim_bits, &lim_f, sizeof lim_f);
        (void)lim_bits;
        /* take_force */
        x = float_of_f64(xd);
        memcpy(&xb, &x, sizeof xb);
        axb = xb & 0x7FFFFFFFUL;
        memcpy(&ax, &axb, sizeof ax);
        ax *= c;
        memcpy(&axb, &ax, sizeof axb);
        if (axb >= floor_bits) {
            n = lim_n;
        } else {
            n = (uint16_t)(ax + 0.5f);
        }
        dir = !(xb >> 31) && (xb & 0x7FFFFFFFUL) != 0;
        printf("%u %u\n", (unsigned)n, dir);
    }
    return 0;
}
"""


@pytest.fixture(scope="module")
def firmware(tmp_path_factory):
    """The compiled helper: ``run(forces, scale32, limit) -> (n, dir)`` arrays."""
    d = tmp_path_factory.mktemp("fwforce")
    (d / "helper.c").write_text(HELPER)
    exe = d / "helper"
    cmd = [CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", "-ffp-contract=off",
           "-I", str(CDIR), str(d / "helper.c"), str(CDIR / "hproto.c"), "-o", str(exe)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr

    def run(forces, scale32, limit):
        sb = struct.unpack("<I", struct.pack("<f", scale32))[0]
        lb = struct.unpack("<Q", struct.pack("<d", limit))[0]
        xs = np.asarray(forces, np.float64).view(np.uint64)
        lines = "".join(f"{int(v) >> 32:x} {int(v) & 0xFFFFFFFF:x} {sb:x} {lb >> 32:x} "
                        f"{lb & 0xFFFFFFFF:x}\n" for v in xs)
        out = subprocess.run([str(exe)], input=lines, capture_output=True, text=True,
                             check=True).stdout.split()
        a = np.array(out, dtype=np.int64).reshape(-1, 2)
        return a[:, 0], a[:, 1]
    return run


def _scales(rng):
    """The Hapkit's step (HELLO.force_scale: 22.7 mN, a binary32) and random others."""
    hapkit = float(np.float32(5.8140e0 / 256))        # about 22.7 mN, any binary32 will do
    return [hapkit] + [float(np.float32(s)) for s in rng.uniform(1e-3, 0.1, 5)]


def _forces(rng, scale, n):
    """Random forces, exact half-steps (in binary64 and their binary32 neighbours) and
    forces at the limit, both signs [N]."""
    k = rng.integers(0, 300, n)
    half = (k + 0.5) * scale
    near = np.nextafter(half.astype(np.float32), np.float32(np.inf)).astype(np.float64)
    below = np.nextafter(half.astype(np.float32), np.float32(0)).astype(np.float64)
    rand = rng.uniform(0, 300 * scale, n)
    whole = k * scale
    x = np.concatenate([half, near, below, rand, whole, [0.0, 1e300, np.float64(3.5e38)]])
    return x * np.where(rng.random(x.size) < 0.5, -1.0, 1.0)


@pytest.mark.parametrize("limit_factor", [np.inf, 1.0, 0.37])
def test_the_host_names_the_firmware_step_for_every_force(firmware, limit_factor):
    """Property over random forces, half-steps included, at several actuator resolutions
    and force limits: ``firmware_force`` is sign * n * scale with the firmware's own n."""
    rng = np.random.default_rng(19)
    for scale in _scales(rng):
        fmax = scale * 256
        limit = fmax * limit_factor if np.isfinite(limit_factor) else 1e300
        x = _forces(rng, scale, 400)
        n, up = firmware(x, scale, limit)
        want = np.where(up == 1, 1.0, -1.0) * n * scale
        want = np.where(n == 0, 0.0, want)
        got = firmware_force(x, scale, min(limit, float(np.float32(fmax))))
        bad = np.flatnonzero(got != want)
        assert bad.size == 0, (scale, x[bad[:5]], got[bad[:5]], want[bad[:5]])


def test_half_steps_are_where_binary64_rounding_names_another_step(firmware):
    """The defect this replaces, shown: near half-steps the binary64 nearest multiple
    (ties to even) and the firmware disagree, by a whole step (22.7 mN for the Hapkit)."""
    rng = np.random.default_rng(7)
    scale = _scales(rng)[0]
    x = _forces(rng, scale, 400)
    n, up = firmware(x, scale, 1e300)
    want = np.where(up == 1, 1.0, -1.0) * n * scale
    old = np.round(x / scale) * scale
    fin = np.abs(x) < 256 * scale
    assert np.any(old[fin] != want[fin])
    assert np.all(firmware_force(x[fin], scale) == np.where(n[fin] == 0, 0.0, want[fin]))


def test_the_account_of_a_framed_device_applies_the_firmware_step():
    """account_from_force_seq with HELLO.force_scale applies firmware_force's steps."""
    scale = float(np.float32(0.0227))
    rng = np.random.default_rng(3)
    f = (rng.integers(-50, 50, 200) + 0.5) * scale
    seq = np.arange(200)
    fseq = np.maximum(seq - 2, 0)
    st = np.where(seq >= 2, fp.STATUS_ARMED | fp.STATUS_FORCE_APPLIED, fp.STATUS_ARMED)
    acc = account_from_force_seq(seq, f, fseq, st, force_scale=scale)
    assert acc.delay == 2
    np.testing.assert_array_equal(acc.applied[2:], firmware_force(f, scale)[:-2])


def test_a_bad_scale_is_refused():
    with pytest.raises(ValueError, match="force_scale"):
        firmware_force([1.0], 0.0)
