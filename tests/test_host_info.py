"""`learning.host_info`: the CPU and maths-library path recorded in every run's summary."""

from __future__ import annotations

from hammer.learning.host_info import cpu_info, host_info

CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 167
model name\t: Test CPU @ 2.0GHz
stepping\t: 1
microcode\t: 0x1
flags\t\t: fpu vme sse2 ssse3 sse4_1 fma avx avx2 avx512f avx512_vnni amx_tile bmi2 lahf_lm

processor\t: 1
model name\t: Test CPU @ 2.0GHz
"""


def test_cpu_info_reads_model_and_only_the_simd_flags(tmp_path):
    f = tmp_path / "cpuinfo"
    f.write_text(CPUINFO)
    info = cpu_info(f)
    assert info["model"] == "Test CPU @ 2.0GHz" and info["vendor"] == "GenuineIntel"
    assert info["family_model_stepping"] == ["6", "167", "1"]
    assert info["simd_flags"] == ["amx_tile", "avx", "avx2", "avx512_vnni", "avx512f", "bmi2", "fma", "sse2",
                                  "sse4_1", "ssse3"]
    assert "model" in cpu_info(tmp_path / "missing")  # no /proc/cpuinfo: still a dict


def test_host_info_names_the_threads_and_libraries(monkeypatch):
    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")
    import torch

    info = host_info()
    assert info["env"]["MKL_CBWR"] == "COMPATIBLE"
    assert info["torch"]["num_threads"] == torch.get_num_threads()
    assert info["torch"]["onednn"].startswith("v")
    assert info["numpy"]["blas"]["name"]
