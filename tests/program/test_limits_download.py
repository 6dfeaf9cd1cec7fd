"""Downloads bounded before they cost anything (issue 28): the size limits of the expanded
program (program/sizes.py), each refusal located at the item that went over and naming the
limit; the user mistakes that were "internal compiler error"; the compile process's memory
and CPU budgets, on a real compile process."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest

from softplc.bench.onlinebench import ring_program
from softplc.core.lifecycle import Command
from softplc.core.problems import Problem, ProgramError
from softplc.core.snapshot import CommandRequest
from softplc.program import bundle as bundles
from softplc.program import wire
from softplc.program.compiler import compile_file, compile_text
from softplc.program.sizes import DEFAULT_SIZES
from softplc.runtime.compileproc import CompileProcess
from softplc.runtime.config import LoopConfig
from softplc.runtime.prepare import CompilerFailed, Preparer

ROOT = Path(__file__).resolve().parents[2]
IO = (ROOT / "io_images" / "transport.yaml").read_text(encoding="utf-8")


def refused(call: object, *args: object) -> Problem:
    """The one problem of a refused compile, which must come quickly."""
    began = time.monotonic()
    with pytest.raises(ProgramError) as caught:
        call(*args)  # type: ignore[operator]
    assert time.monotonic() - began < 15
    (problem,) = caught.value.problems
    return problem


def test_the_benchs_10000_transition_ring_is_allowed() -> None:
    net = compile_text(ring_program(10_000, 1), str(ROOT / "programs" / "ring.yaml"), ROOT)
    assert (len(net.transitions), len(net.place_names)) == (10_000, 10_001)


def test_the_shipped_programs_are_far_below_the_limits() -> None:
    for path in sorted((ROOT / "programs").glob("*.yaml")):
        net = compile_file(path, ROOT)
        assert len(net.place_names) * 10 < DEFAULT_SIZES.places, path


def test_a_20000_place_download_is_refused_at_the_place_over_the_limit() -> None:
    problem = refused(compile_text, ring_program(20_000, 0),
                      str(ROOT / "programs" / "ring.yaml"), ROOT)
    assert (Path(problem.file).name, problem.line, problem.path) == (
        "ring.yaml", 16_004, "places.p16000")  # 3 lines of header, then p0 ...
    assert "16,001 places" in problem.message and "places = 16,000" in problem.message


def _subnet_tree(tmp_path: Path) -> Path:
    """10 x 10 x 10 instances of a 100-transition leaf: a few KB of files, 100,000 transitions
    once expanded."""
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    leaf = ["places:"] + [f"  q{i}: {{}}" for i in range(10)] + ["transitions:"]
    leaf += [f"  t{i}: {{from: [q{i % 10}], to: [q{(i + 1) % 10}]}}" for i in range(100)]
    (tmp_path / "leaf.yaml").write_text("\n".join(leaf) + "\n", encoding="utf-8")
    for name, child in (("mid.yaml", "leaf.yaml"), ("top.yaml", "mid.yaml")):
        lines = ["subnets:"] + [f"  s{i}: {{net: {child}}}" for i in range(10)]
        (tmp_path / name).write_text("\n".join(lines) + "\n", encoding="utf-8")
    lines = ["program: bomb", "io_image: io.yaml", "places: {}", "subnets:"]
    lines += [f"  s{i}: {{net: top.yaml}}" for i in range(10)]
    (tmp_path / "main.yaml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return tmp_path / "main.yaml"


def test_a_100000_transition_subnet_tree_stops_at_the_transition_limit(tmp_path: Path) -> None:
    main = _subnet_tree(tmp_path)
    assert sum(p.stat().st_size for p in tmp_path.iterdir() if p.name != "io.yaml") < 6_000
    problem = refused(compile_file, main, tmp_path)
    assert (Path(problem.file).name, problem.path) == ("leaf.yaml", "transitions.t0")
    assert "16,001 transitions" in problem.message and "transitions = 16,000" in problem.message


def test_the_same_tree_as_a_bundle_download_is_refused_with_the_limit(tmp_path: Path) -> None:
    (tmp_path / "src").mkdir()
    blob = bundles.pack(bundles.from_files(_subnet_tree(tmp_path / "src")))
    prep = Preparer(LoopConfig(root=str(tmp_path), state_dir=str(tmp_path / "state")),
                    lambda: None, lambda: ())
    problem = refused(prep.compile_bundle, blob)
    assert "transitions = 16,000" in problem.message


def test_subnet_instances_have_a_limit(tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "one.yaml").write_text("places: {x: {}}\n", encoding="utf-8")
    lines = ["program: many", "io_image: io.yaml", "subnets:"]
    lines += [f"  s{i}: {{net: one.yaml}}" for i in range(1_001)]
    (tmp_path / "main.yaml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    problem = refused(compile_file, tmp_path / "main.yaml", tmp_path)
    assert (problem.line, problem.path) == (1_004, "subnets.s1000")
    assert "1,001 subnet instances" in problem.message and "subnets = 1,000" in problem.message


def test_arcs_have_a_limit() -> None:
    arcs = ", ".join(["a"] * 65)
    lines = ["program: arcs", "io_image: ../io_images/transport.yaml", "places:",
             "  a: {tokens: 1}", "transitions:"]
    lines += [f"  t{i}: {{from: [{arcs}], to: [a]}}" for i in range(1_000)]
    problem = refused(compile_text, "\n".join(lines), str(ROOT / "programs" / "arcs.yaml"),
                      ROOT)
    assert problem.path == "transitions.t969"  # 970 x 66 arcs > 64,000
    assert "arcs = 64,000" in problem.message


def test_expression_characters_have_a_limit() -> None:
    guard = " or ".join(["true"] * 250)  # 1,996 characters: each under the 2,000 of one
    lines = ["program: guards", "io_image: ../io_images/transport.yaml", "places:",
             "  a: {tokens: 1}", "transitions:"]
    lines += [f"  t{i}: {{from: [a], to: [a], when: '{guard}'}}" for i in range(1_100)]
    problem = refused(compile_text, "\n".join(lines), str(ROOT / "programs" / "g.yaml"), ROOT)
    assert problem.path == "transitions.t1002.when"  # 1,003 x 1,996 > 2,000,000
    assert "expression_chars = 2,000,000" in problem.message


def test_program_text_has_a_limit_checked_before_parsing() -> None:
    text = "program: big\n" + "# padding\n" * 400_001
    problem = refused(compile_text, text, str(ROOT / "programs" / "big.yaml"), ROOT)
    assert problem.line == 1 and "text_chars = 4,000,000" in problem.message


def test_a_guard_of_ten_thousand_nots_is_a_located_problem() -> None:
    lines = ["program: nots", "io_image: ../io_images/transport.yaml", "places:",
             "  a: {tokens: 1}", "transitions:",
             f"  t: {{from: [a], to: [a], when: '{'not ' * 10_000}true'}}"]
    with pytest.raises(ProgramError) as caught:  # was a MemoryError: internal compiler error
        compile_text("\n".join(lines), str(ROOT / "programs" / "nots.yaml"), ROOT)
    (problem,) = caught.value.problems
    assert (problem.line, problem.path) == (6, "transitions.t.when")
    assert "expression longer than 2000 characters" in problem.message


def _zip(files: dict[str, bytes]) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive:
        for name, data in files.items():
            archive.writestr(name, data)
    return out.getvalue()


def test_a_bundle_with_a_file_and_a_folder_of_the_same_name_is_refused(
        tmp_path: Path) -> None:
    blob = _zip({bundles.MANIFEST: json.dumps({"format": 1, "program": "main.yaml"}).encode(),
                 "main.yaml": b"program: x\nio_image: io/p.yaml\n",
                 "io": b"a file", "io/p.yaml": IO.encode()})
    prep = Preparer(LoopConfig(root=str(tmp_path), state_dir=str(tmp_path / "state")),
                    lambda: None, lambda: ())
    problem = refused(prep.compile_bundle, blob)
    assert problem.message == "bundle: 'io' is a file and also the folder of 'io/p.yaml'"
    assert not (tmp_path / "state" / "bundles").exists() or \
        not any((tmp_path / "state" / "bundles").iterdir())  # nothing unpacked


def test_a_bundle_that_cannot_be_written_is_refused_not_an_internal_error(
        tmp_path: Path) -> None:
    # A full disk, for real: the child may write files of at most 1 KB (RLIMIT_FSIZE; SIGXFSZ
    # ignored, so the write fails with EFBIG as it fails with ENOSPC on a full disk).
    script = (
        "import resource, signal, sys\n"
        "from softplc.program import bundle\n"
        "from softplc.core.problems import ProgramError\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (1024, resource.RLIM_INFINITY))\n"
        "b = bundle.Bundle('main.yaml', {'main.yaml': b'#' * 4096})\n"
        "try:\n"
        "    bundle.extract(b, sys.argv[1])\n"
        "except ProgramError as exc:\n"
        "    print(exc.problems[0].message)\n")
    out = subprocess.run([sys.executable, "-c", script, str(tmp_path / "unpacked")],
                         capture_output=True, text=True, timeout=20, check=False, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "bundle: cannot be unpacked on the server: File too large"
    assert not (tmp_path / "unpacked").exists()  # nothing half-written is left in place


def _download(text: str) -> CommandRequest:
    return CommandRequest(1, Command.DOWNLOAD, program_text=text, program_path="ring.yaml")


def test_a_compile_over_the_memory_budget_is_refused_and_the_next_one_served() -> None:
    compiler = CompileProcess(LoopConfig(root=str(ROOT)), memory_bytes=64 << 20)
    try:  # a 2,000-transition ring: the analysis gate's four 2,000 x 2,000 arrays are 128 MB
        began = time.monotonic()
        with pytest.raises(CompilerFailed, match="more memory than the compile process's "
                                                 "budget of 64 MiB"):
            compiler.build(_download(ring_program(2_000, 0)))
        assert time.monotonic() - began < 15
        assert wire.loads(compiler.build(_download(ring_program(10, 0))).net).transitions
        assert compiler.started == 2  # the one at its limit ended; a new one compiled it
    finally:
        compiler.close()


def _toggles_program(n: int = 12) -> str:
    """n places that toggle under guards over a word (free in the analysis): 2^n states with
    2^n candidate sets each. The gate spends its work budget on it: seconds of CPU."""
    lines = ["program: toggles", "io_image: ../io_images/transport.yaml", "places:"]
    lines += [f"  a{i}: {{tokens: 1}}" for i in range(n)] + [f"  b{i}: {{}}" for i in range(n)]
    lines += ["transitions:"]
    for i in range(n):
        lines += [f"  on{i}: {{from: [a{i}], to: [b{i}], when: 'parts_delivered > {i}'}}",
                  f"  off{i}: {{from: [b{i}], to: [a{i}], when: 'parts_delivered < {i}'}}"]
    return "\n".join(lines) + "\n"


def test_a_compile_over_the_cpu_budget_is_refused_and_the_process_lives_on() -> None:
    compiler = CompileProcess(LoopConfig(root=str(ROOT)), cpu_s=0.5)
    try:  # the budget leaves 0.5 to 1.5 s of CPU (RLIMIT_CPU counts whole seconds)
        # The refusal names the CPU budget: it came from RLIMIT_CPU, not from the compile
        # deadline (which says "took longer than"); how long that takes in wall time depends
        # on how busy the machine is (nice 10: seconds beside busy loops).
        with pytest.raises(CompilerFailed, match=r"CPU budget of 0\.5 s"):
            compiler.build(_download(_toggles_program()))
        pid = compiler.pid
        assert wire.loads(compiler.build(_download(ring_program(10, 0))).net).transitions
        assert (compiler.pid, compiler.started) == (pid, 1)
    finally:
        compiler.close()


# -- a bundle's limits at their edges (issue 43: the literal values, so a moved limit fails) --

def _bundle_of(files: dict[str, bytes]) -> bytes:
    return bundles.pack(bundles.Bundle("main.yaml", {"main.yaml": b"x", **files}))


def test_a_bundle_file_of_exactly_1_mib_is_taken_and_one_byte_more_refused() -> None:
    taken = bundles.unpack(_bundle_of({"big.bin": b"\0" * 1_048_576}))
    assert len(taken.files["big.bin"]) == 1_048_576
    with pytest.raises(bundles.BundleError,
                       match=r"^bundle: 'big.bin' is larger than 1048576 bytes$"):
        bundles.unpack(_bundle_of({"big.bin": b"\0" * 1_048_577}))


def test_a_bundle_of_64_files_is_taken_and_65_refused() -> None:
    files = {f"f{n:02d}.txt": b"" for n in range(63)}  # and main.yaml: 64
    assert len(bundles.unpack(_bundle_of(files)).files) == 64
    with pytest.raises(bundles.BundleError, match=r"^bundle: 65 files, at most 64 expected$"):
        bundles.unpack(_bundle_of({**files, "f63.txt": b""}))


def test_a_bundle_of_exactly_4_mib_unpacked_is_taken_and_one_byte_more_refused() -> None:
    manifest = len(json.dumps({"format": 1, "program": "main.yaml"}, sort_keys=True))
    mib = b"\0" * 1_048_576
    rest = 4_194_304 - manifest - 1 - 3 * 1_048_576  # the manifest and main.yaml count too
    files = {"a.bin": mib, "b.bin": mib, "c.bin": mib}
    assert len(bundles.unpack(_bundle_of({**files, "d.bin": b"\0" * rest})).files) == 5
    with pytest.raises(bundles.BundleError,
                       match=r"^bundle: 4194305 bytes unpacked, at most 4194304$"):
        bundles.unpack(_bundle_of({**files, "d.bin": b"\0" * (rest + 1)}))


def test_a_bundle_manifest_of_4095_bytes_is_taken_and_4096_refused() -> None:
    text = json.dumps({"format": 1, "program": "main.yaml"})
    for size, taken in ((4095, True), (4096, False)):
        blob = _zip({bundles.MANIFEST: text.ljust(size).encode(), "main.yaml": b"x"})
        if taken:
            assert bundles.unpack(blob).program == "main.yaml"
        else:
            with pytest.raises(bundles.BundleError, match=r"is larger than 4095 bytes$"):
                bundles.unpack(blob)


def test_a_bundle_member_that_cannot_be_read_or_appears_twice_is_refused() -> None:
    manifest = json.dumps({"format": 1, "program": "main.yaml"}).encode()
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        archive.writestr(bundles.MANIFEST, manifest)
        archive.writestr("main.yaml", b"program: hello world\n")
    damaged = out.getvalue().replace(b"hello world", b"hellO world")  # its CRC fails
    with pytest.raises(bundles.BundleError,
                       match=r"^bundle: 'main.yaml' cannot be read \(Bad CRC-32"):
        bundles.unpack(damaged)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive, pytest.warns(UserWarning, match="Duplicate"):
        archive.writestr(bundles.MANIFEST, manifest)
        archive.writestr("main.yaml", b"x")
        archive.writestr("main.yaml", b"y")
    with pytest.raises(bundles.BundleError, match=r"^bundle: 'main.yaml' appears twice$"):
        bundles.unpack(out.getvalue())


def test_a_bundle_unpacks_and_writes_out_files_in_folders(tmp_path: Path) -> None:
    bundle = bundles.Bundle("main.yaml", {"main.yaml": b"m", "io/deep/p.yaml": b"p"})
    program = bundles.extract(bundle, tmp_path / "unpacked")
    assert program == tmp_path / "unpacked" / "main.yaml"
    assert (tmp_path / "unpacked" / "io" / "deep" / "p.yaml").read_bytes() == b"p"
    written = bundles.write_out(bundle, tmp_path / "out")
    assert written == [tmp_path / "out" / "io" / "deep" / "p.yaml", tmp_path / "out" / "main.yaml"]
    assert written[0].read_bytes() == b"p"


def test_a_local_bundle_of_64_files_is_taken_and_65_refused(tmp_path: Path) -> None:
    for subnets, taken in ((62, True), (63, False)):  # with main.yaml and io.yaml: 64, 65
        directory = tmp_path / str(subnets)
        directory.mkdir()
        (directory / "io.yaml").write_text(IO)
        (directory / "main.yaml").write_text("program: m\nio_image: io.yaml\nsubnets:\n" + "".join(
            f"  s{n}: {{net: nets/s{n}.yaml}}\n" for n in range(subnets)))
        (directory / "nets").mkdir()
        for n in range(subnets):
            (directory / "nets" / f"s{n}.yaml").write_text("places: {}\n")
        if taken:
            assert len(bundles.from_files(directory / "main.yaml").files) == 64
        else:
            with pytest.raises(bundles.BundleError,
                               match=r"^bundle: 65 files, at most 64 expected$"):
                bundles.from_files(directory / "main.yaml")
