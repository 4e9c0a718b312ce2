"""The dialogue-line manifest: rows over command-line defaults, one error listing every bad
row, relative paths, the line key and the ledger of lines done; on real speech files."""

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from diffsheg_core.errors import DiffshegError
from diffsheg_core.foppas import PRESETS as FOPPAS_PRESETS
from diffsheg_core.ledger import Ledger, line_key, stage_name, staged_path
from diffsheg_core.manifest import OUTPUTS, Line, ManifestError, read_manifest, with_settings
from diffsheg_core.settings import GenerateSettings

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
AUDIO = DATA / "audio" / "lang"
SPEECH = (AUDIO / "ru_golos_1.wav").resolve()
SPEECH2 = (AUDIO / "zh_aishell_1.wav").resolve()
PRESETS = ("beat", "rigify", "mixamo")
STYLES = ("calm", "conversational", "animated")
HEADER = "id,audio,blend,armature,face,preset,style,seed,steps,gesture_energy,start_frame,every_frame,outputs\n"


@pytest.fixture
def project(tmp_path) -> Path:
    """A folder with a character .blend (any bytes: the manifest only checks and hashes it)."""
    (tmp_path / "chars").mkdir()
    (tmp_path / "chars" / "hero.blend").write_bytes(b"BLENDER-v300 not a real scene\x00" * 10)
    return tmp_path


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def test_a_row_overrides_the_command_line_defaults(project):
    manifest = write(project / "lines.csv", HEADER +
                     f"l1,{SPEECH},chars/hero.blend,Rig,Head;Teeth,beat,calm,7,,0.4,101,yes,npz;glb\n"
                     f"l2,{SPEECH2},,,,,,,,,,,\n")
    defaults = {"seed": 3, "steps": 5, "outputs": "npz", "style": "animated", "preset": "rigify",
                "face": ["Face"], "max_error": 2.0, "audio": "ignored.wav", "no_render": True}
    one, two = read_manifest(manifest, defaults, PRESETS, STYLES)
    assert one.id == "l1" and one.audio == SPEECH and one.blend == project / "chars" / "hero.blend"
    assert one.settings == GenerateSettings(seed=7, steps=5, style="calm", skip_guidance=0.4)
    assert (one.armature, one.face, one.preset) == ("Rig", ("Head", "Teeth"), "beat")
    assert (one.start_frame, one.every_frame, one.max_error, one.outputs) == (101, True, 2.0, ("glb", "npz"))
    # the row that gives nothing takes every default
    assert two.settings == GenerateSettings(seed=3, steps=5, style="animated")
    assert (two.blend, two.face, two.preset, two.outputs, two.every_frame) == (None, ("Face",), "rigify", ("npz",), False)
    assert (two.start_frame, two.max_face_error) == (None, 0.02)


def test_csv_and_json_lines_read_the_same(project):
    csv_path = write(project / "lines.csv", HEADER +
                     f"a,{SPEECH},chars/hero.blend,Rig,Head;Teeth,beat,calm=0.7;x,7,5,0.4,1,0,npz;blend\n"
                     .replace("calm=0.7;x", '"calm=0.7,animated=0.3"'))
    rows = [{"id": "a", "audio": str(SPEECH), "blend": "chars/hero.blend", "armature": "Rig",
             "face": ["Head", "Teeth"], "preset": "beat", "style": {"calm": 0.7, "animated": 0.3}, "seed": 7,
             "steps": 5, "gesture_energy": 0.4, "start_frame": 1, "every_frame": False, "outputs": ["blend", "npz"]}]
    jsonl_path = write(project / "lines.jsonl", "\n".join(json.dumps(r) for r in rows) + "\n\n")
    from_csv = read_manifest(csv_path, {}, PRESETS, STYLES)
    from_jsonl = read_manifest(jsonl_path, {}, PRESETS, STYLES)
    assert [replace(line, row=0) for line in from_csv] == [replace(line, row=0) for line in from_jsonl]
    assert from_csv[0].settings.style == {"calm": 0.7, "animated": 0.3}
    # JSON Lines may spell a setting as the command line does, too
    text_style = write(project / "text.jsonl", json.dumps({**rows[0], "style": "calm=0.7,animated=0.3"}) + "\n")
    assert read_manifest(text_style, {}, PRESETS, STYLES)[0].settings == from_csv[0].settings


def test_three_kinds_of_bad_rows_are_listed_in_one_error_before_anything_runs(project):
    manifest = write(project / "lines.csv", HEADER +
                     f"ok,{SPEECH},,,,,,,,,,,npz\n"
                     f"missing,{AUDIO / 'no_such_line.wav'},,,,,,,,,,,npz\n"   # a missing file
                     f"preset,{SPEECH},chars/hero.blend,,,unreal_mannequin,,,,,,,blend\n"  # an unknown preset
                     f"ok,{SPEECH2},,,,,,,,,,,npz\n"                       # a duplicate id
                     f"number,{SPEECH},,,,,,,2000,,,,npz\n")                # a number out of range
    with pytest.raises(ManifestError) as caught:
        read_manifest(manifest, {}, PRESETS, STYLES)
    problems = caught.value.problems
    assert len(problems) == 4, problems
    assert problems[0].startswith("row 3, column audio:") and "no_such_line.wav' does not exist" in problems[0]
    assert problems[1].startswith("row 4, column preset: unknown preset 'unreal_mannequin'")
    assert problems[2] == "row 5, column id: duplicate id 'ok' (also on row 2)"
    assert problems[3] == "row 6, column steps: steps must be a whole number from 1 to 1000, got 2000"
    assert str(caught.value).splitlines()[1:] == problems  # one per line, after the summary


def test_every_other_kind_of_bad_row_is_found_too(project):
    unreadable = project / "empty.wav"
    unreadable.write_bytes(b"")
    manifest = write(project / "lines.csv", "id,audio,style,style_at,seed,every_frame,outputs,colour\n"
                     f",{SPEECH},,,,,npz,\n"                                   # empty id
                     f"a,{unreadable},,,,,npz,\n"                              # an empty audio file
                     f"b,{SPEECH},loud,,,,npz,\n"                              # an unknown style
                     f"c,{SPEECH},,\"0=calm,2=shouty\",,,npz,\n"               # ... and in style_at
                     f"d,{SPEECH},,,-1,maybe,npz;fbx,\n"                       # seed, flag, output
                     f"e,{SPEECH},,,,,glb,\n"                                  # glb needs a character
                     f"f/../g,{SPEECH},,,,,npz,\n")                            # an id that is no file name
    with pytest.raises(ManifestError) as caught:
        read_manifest(manifest, {}, PRESETS, STYLES)
    text = str(caught.value)
    for expected in ("row 1 (header), column colour: unknown column", "row 2, column id: empty id",
                     "row 3, column audio:", "is empty (0 bytes)", "row 4, column style: unknown style 'loud'",
                     "row 5, column style_at: unknown style 'shouty'", "row 6, column seed: seed must be a whole number",
                     "row 6, column every_frame:", "row 6, column outputs: unknown output 'fbx'",
                     "row 7, column blend: the outputs glb key the motion onto a character",
                     "row 8, column id: id 'f/../g' cannot name a file"):
        assert expected in text, expected
    # without the model's style names, style names are left to the model
    ok = write(project / "ok.csv", f"id,audio,style,outputs\nb,{SPEECH},loud,npz\n")
    assert read_manifest(ok, {}, PRESETS, None)[0].settings.style == "loud"


def test_relative_paths_resolve_against_the_manifest_folder(project, monkeypatch):
    folder = project / "manifests" / "episode1"
    manifest = write(folder / "lines.csv", "id,audio,blend,preset,outputs\n"
                     f"a,{os.path.relpath(SPEECH, folder)},../../chars/hero.blend,beat,blend\n")
    monkeypatch.chdir(DATA)  # not the working folder
    (line,) = read_manifest(manifest, {}, PRESETS, STYLES)
    assert line.audio == SPEECH and line.blend == (project / "chars" / "hero.blend").resolve()
    # a preset may be a .json file, beside the manifest
    write(folder / "studio_rig.json", "{}")
    write(folder / "lines.csv", f"id,audio,preset,outputs\na,{os.path.relpath(SPEECH, folder)},studio_rig.json,npz\n")
    assert read_manifest(manifest, {}, PRESETS, STYLES)[0].preset == str(folder.resolve() / "studio_rig.json")


def line_of(project: Path, audio: Path, **fields) -> Line:
    row = {"id": "l1", "audio": str(audio), "blend": "chars/hero.blend", "preset": "beat", "seed": 2,
           "steps": 5, "outputs": "blend;npz", **fields}
    manifest = write(project / "one.jsonl", json.dumps(row) + "\n")
    (line,) = read_manifest(manifest, {}, PRESETS, STYLES)
    return line


def test_the_key_changes_with_audio_bytes_a_setting_or_an_output_and_not_otherwise(project):
    audio = project / "line.wav"
    shutil.copyfile(SPEECH, audio)
    line = line_of(project, audio)
    key = line_key(line)
    assert len(key) == 64 and line_key(line) == key
    # not otherwise: the same bytes elsewhere, outputs in another order, another id, thread count
    copy = project / "elsewhere" / "same.wav"
    copy.parent.mkdir()
    shutil.copyfile(audio, copy)
    assert line_key(line_of(project, copy)) == key
    assert line_key(line_of(project, audio, outputs="npz;blend", id="other")) == key
    assert line_key(with_settings(line, threads=4)) == key
    # a setting, an output, a keying option, the character's bytes
    changed = {line_key(with_settings(line, seed=3)), line_key(with_settings(line, style="calm")),
               line_key(line_of(project, audio, outputs="blend;npz;glb")),
               line_key(line_of(project, audio, max_error=0.5)), line_key(replace(line, face=("Head",)))}
    assert key not in changed and len(changed) == 5
    (project / "chars" / "hero.blend").write_bytes(b"another character")
    assert line_key(line) not in changed | {key}
    (project / "chars" / "hero.blend").write_bytes(b"BLENDER-v300 not a real scene\x00" * 10)
    assert line_key(line) == key
    # the audio's bytes: one sample changed
    data = bytearray(audio.read_bytes())
    data[-2] ^= 0x01
    audio.write_bytes(bytes(data))
    assert line_key(line) != key


def test_the_ledger_skips_done_lines_redoes_changed_ones_and_survives_a_torn_last_line(project):
    out = project / "out"
    audio = project / "line.wav"
    shutil.copyfile(SPEECH, audio)
    first, second = line_of(project, audio), replace(line_of(project, SPEECH2), id="l2")
    ledger = Ledger(out)
    assert not ledger.done(first) and not ledger.done(second)
    ledger.record(first, [out / "l1.npz", out / "l1.blend"])
    assert ledger.done(first) and not ledger.done(second)
    entry = json.loads((out / "done.jsonl").read_text().splitlines()[0])
    assert entry["id"] == "l1" and entry["key"] == line_key(first) and entry["outputs"][0].endswith("l1.npz")
    assert entry["time"]
    # a new run reads it back: done stays done; a changed setting or audio is redone
    ledger = Ledger(out)
    assert ledger.done(first)
    assert not ledger.done(with_settings(first, seed=9))
    assert not ledger.done(replace(first, id="renamed"))
    # a driver killed while appending leaves half a line: ignored, and the next record stays whole
    with open(out / "done.jsonl", "ab") as fh:
        fh.write(b'{"id": "l2", "key": "' + line_key(second)[:20].encode())
    ledger = Ledger(out)
    assert ledger.done(first) and not ledger.done(second)
    ledger.record(second, [out / "l2.npz"])
    ledger = Ledger(out)
    assert ledger.done(first) and ledger.done(second)
    data = bytearray(audio.read_bytes())
    data[-2] ^= 0x01
    audio.write_bytes(bytes(data))
    assert not Ledger(out).done(first)  # its audio changed: redo
    ledger.record(first, [])
    assert Ledger(out).done(first)      # the latest record of an id wins


def test_an_output_that_cannot_be_put_in_place_is_put_there_next_run_or_the_line_redone(project):
    """Staged beside their final names; a folder at one output's name fails the commit by
    name, the line stays recorded and its staged file kept; the next run's recovery puts it
    in place, or (still blocked) forgets the line so it is done again; unrecorded attempts'
    staged files and partial files are removed."""
    out = project / "out"
    out.mkdir()
    line = line_of(project, SPEECH)
    finals = [out / "l1.blend", out / "l1.npz"]
    attempt, dead = stage_name(), stage_name()
    assert attempt != dead
    for name, staged in ((f.name, s) for f in finals for s in (attempt, dead)):
        staged_path(out, staged, name).write_bytes(f"{staged} {name}".encode())
        assert staged_path(out, staged, name).parent == out  # beside the final name
    (out / ".l1.partial.blend").write_bytes(b"torn")
    (out / "l1.npz").mkdir()  # something in the way of one output
    ledger = Ledger(out)
    with pytest.raises(DiffshegError, match=r"cannot put l1.npz in place .*Is a directory.*the next run puts it"):
        ledger.commit(line, attempt, finals)
    assert ledger.done(line) and (out / "l1.blend").read_bytes() == f"{attempt} l1.blend".encode()
    ledger.clean_staging()  # the end of the run: the recorded attempt's file stays, the dead one's goes
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".staged-")) == \
        [staged_path(out, attempt, "l1.npz").name]

    problems = Ledger(out).recover()  # still blocked: forgotten, to be done again
    assert len(problems) == 1 and problems[0].startswith("l1: cannot put l1.npz") and "again" in problems[0]
    assert not Ledger(out).done(line)
    assert sorted(p.name for p in out.iterdir()) == ["done.jsonl", "l1.blend", "l1.npz"]  # nothing staged
    # done again, blocked again; the folder removed, the next run puts the output in place
    staged_path(out, attempt, "l1.npz").write_bytes(b"again")
    with pytest.raises(DiffshegError):
        Ledger(out).commit(line, attempt, finals)
    (out / "l1.npz").rmdir()
    assert Ledger(out).recover() == []
    assert Ledger(out).done(line) and (out / "l1.npz").read_bytes() == b"again"
    assert sorted(p.name for p in out.iterdir()) == ["done.jsonl", "l1.blend", "l1.npz"]


def test_the_output_kinds():
    assert OUTPUTS == ("blend", "fbx_unreal", "fbx_unity", "glb", "npz", "arkit_json", "csv", "mp4")


def test_emotion_columns_are_read_and_checked_as_the_command_line_does(project):
    manifest = write(project / "lines.csv", "id,audio,emotion,emotion_at,outputs\n"
                     f"a,{SPEECH},sad=0.6,\"0=happy,2=angry=0.5\",npz\n"
                     f"b,{SPEECH},,,npz\n"
                     f"c,{SPEECH},joyful,,npz\n"
                     f"d,{SPEECH},,0=sad=3,npz\n")
    with pytest.raises(ManifestError) as caught:
        read_manifest(manifest, {"emotion": "happy"}, PRESETS, STYLES)
    text = str(caught.value)
    assert "row 4, column emotion: unknown emotion 'joyful'" in text
    assert "row 5, column emotion_at: the intensity of emotion 'sad' must be a number from 0 to 1" in text
    good = write(project / "good.csv", "\n".join(manifest.read_text().splitlines()[:3]) + "\n")
    a, b = read_manifest(good, {"emotion": "happy"}, PRESETS, STYLES)
    assert a.settings.emotion == {"sad": 0.6} and a.settings.emotion_at == ((0.0, {"happy": 1.0}),
                                                                           (2.0, {"angry": 0.5}))
    assert b.settings.emotion == {"happy": 1.0}  # the command line's default
    assert line_key(a) != line_key(replace(a, settings=replace(a.settings, emotion={"sad": 0.7})))


def test_the_language_column_names_a_face_the_model_carries(project):
    """Issue 42: a row's `language` (a code, any case) over the command line's --language, checked
    as the command line checks it and, given the model's faces (studio.py reads them from its
    file), against those, so a batch names a missing face before anything runs."""
    manifest = write(project / "lines.csv", "id,audio,language,outputs\n"
                     f"a,{SPEECH2}, ZH ,npz\n"
                     f"b,{SPEECH},,npz\n"
                     f"c,{SPEECH},ja,npz\n"
                     f"d,{SPEECH},Mandarin Chinese,npz\n")
    with pytest.raises(ManifestError) as caught:
        read_manifest(manifest, {}, PRESETS, STYLES, languages=["zh"])
    text = str(caught.value)
    assert "row 4, column language: the model has no face of its own for 'ja' (it has: zh)" in text
    assert "row 5, column language: language must be a language code such as zh or pt-br" in text
    a, b, c = read_manifest(write(project / "good.csv", "\n".join(manifest.read_text().splitlines()[:4]) + "\n"),
                            {"language": "ja"}, PRESETS, STYLES)  # no faces given: the model checks when it runs
    assert (a.settings.language, b.settings.language, c.settings.language) == ("zh", "ja", "ja")
    assert line_key(a) != line_key(replace(a, settings=replace(a.settings, language=None)))


def test_the_sampling_column_is_read_and_checked_as_the_command_line_does(project):
    """Issue 39, item 5: a row's `sampling` (fast, quality or an official preset) over the
    command line's --sampling; a bad one is named with its row and the choices, by
    batch_render.py --check too."""
    import subprocess
    import sys

    manifest = write(project / "lines.csv", "id,audio,sampling,outputs\n"
                     f"a,{SPEECH},quality,npz\n"
                     f"b,{SPEECH},,npz\n"
                     f"c,{SPEECH}, Fast ,npz\n"
                     f"d,{SPEECH},no-resample,npz\n")
    a, b, c, d = read_manifest(manifest, {}, PRESETS, STYLES)
    assert [line.settings.sampling for line in (a, b, c, d)] == ["quality", "fast", "fast", "no-resample"]
    assert read_manifest(manifest, {"sampling": "quality"}, PRESETS, STYLES)[1].settings.sampling == "quality"
    assert line_key(a) != line_key(b)  # a line done fast is done again in quality
    jsonl = write(project / "lines.jsonl", json.dumps({"id": "a", "audio": str(SPEECH), "sampling": "quality",
                                                       "outputs": "npz"}) + "\n")
    assert read_manifest(jsonl, {}, PRESETS, STYLES)[0].settings == GenerateSettings(sampling="quality")

    bad = write(project / "bad.csv", manifest.read_text() + f"e,{SPEECH},slow,npz\nf,{SPEECH},25,npz\n")
    with pytest.raises(ManifestError) as caught:
        read_manifest(bad, {}, PRESETS, STYLES)
    assert caught.value.problems == [
        f"row {row}, column sampling: unknown sampling '{value}': use fast (the default), quality (the model's "
        f"own sampling, 25 steps) or an official preset ({', '.join(FOPPAS_PRESETS)})"
        for row, value in ((6, "slow"), (7, "25"))]
    with pytest.raises(ManifestError, match="defaults \\(command line\\), sampling: unknown sampling 'slow'"):
        read_manifest(manifest, {"sampling": "slow"}, PRESETS, STYLES)
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve().parents[1] / "batch_render.py"),
                           "--manifest", str(bad), "--check", "--output", str(project / "out")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "row 6, column sampling: unknown sampling 'slow'" in proc.stderr
    assert "row 7, column sampling: unknown sampling '25'" in proc.stderr
    assert "row 2," not in proc.stderr and not (project / "out").exists()


def test_upper_body_only_is_a_flag_column(project):
    manifest = write(project / "lines.csv", f"id,audio,upper_body_only,outputs\na,{SPEECH},yes,npz\nb,{SPEECH},,npz\n")
    a, b = read_manifest(manifest, {}, PRESETS, STYLES)
    assert a.settings.upper_body_only and not b.settings.upper_body_only
    bad = write(project / "bad.csv", f"id,audio,upper_body_only,outputs\na,{SPEECH},seated,npz\n")
    with pytest.raises(ManifestError, match="row 2, column upper_body_only: upper_body_only must be 1 or 0"):
        read_manifest(bad, {}, PRESETS, STYLES)


def test_no_output_takes_a_name_the_batch_writes_itself_or_another_lines_in_another_case(project):
    """id 'report' with a csv output would be overwritten by the QC report (issue 43, defect
    2); ids differing only in case overwrite each other on Windows and macOS."""
    manifest = write(project / "lines.csv", "id,audio,outputs\n"
                     f"report,{SPEECH},npz;csv\nREPORT,{SPEECH2},csv\nreport2,{SPEECH},csv\n"
                     f"Take,{SPEECH},npz\ntake,{SPEECH2},npz;csv\n")
    with pytest.raises(ManifestError) as caught:
        read_manifest(manifest, {}, PRESETS, STYLES)
    problems = caught.value.problems
    assert problems[:2] == [
        "row 2, column id: the csv output of 'report' would be 'report.csv', which the batch writes itself "
        "(report.csv): rename the line",
        "row 3, column id: the csv output of 'REPORT' would be 'REPORT.csv', which the batch writes itself "
        "(report.csv): rename the line"]
    assert problems[2].startswith("row 6, column id: 'take' and 'Take' (row 5) differ only in case")
    assert len(problems) == 3
    ok = write(project / "ok.csv", f"id,audio,outputs\nreport,{SPEECH},npz;arkit_json\ndone,{SPEECH2},npz\n")
    assert [l.id for l in read_manifest(ok, {}, PRESETS, STYLES)] == ["report", "done"]


def test_ids_too_long_for_a_file_name_are_refused_by_the_check(project):
    longest, too_long = "a" * 190 + "é" * 5, "b" * 199 + "é"  # 200 and 201 bytes (defect 5)
    manifest = write(project / "lines.csv", f"id,audio,outputs\n{longest},{SPEECH},npz\n{too_long},{SPEECH},npz\n")
    with pytest.raises(ManifestError) as caught:
        read_manifest(manifest, {}, PRESETS, STYLES)
    assert caught.value.problems == [f"row 3, column id: id '{too_long[:40]}...' is 201 bytes long, too long to "
                                     "name its files: keep ids to 200 bytes"]


def test_the_check_reports_every_row_where_one_would_have_stopped_it(project):
    """A symlink loop as audio and a JSON row whose id is a list are rows with problems like
    any other, each with its row number (defect 7), beside a corrupt audio file, a text file
    named .blend and an infinite style weight (defect 9)."""
    (project / "loop.wav").symlink_to(project / "loop.wav")
    corrupt = project / "corrupt.wav"
    corrupt.write_bytes(b"RIFF\x00\x00\x00\x00WAVEfmt " + bytes(range(64)))
    (project / "notes.blend").write_text("a text file")
    rows = [{"id": ["a", "b"], "audio": str(SPEECH), "outputs": "npz"},
            {"id": "loop", "audio": "loop.wav", "outputs": "npz"},
            {"id": "corrupt", "audio": str(corrupt), "outputs": "npz"},
            {"id": "text", "audio": str(SPEECH), "blend": "notes.blend", "outputs": "blend"},
            {"id": "inf", "audio": str(SPEECH), "style": "calm=1e309", "outputs": "npz"},
            {"id": "fine", "audio": str(SPEECH), "outputs": "npz"}]
    manifest = write(project / "lines.jsonl", "\n".join(json.dumps(r) for r in rows) + "\n")
    with pytest.raises(ManifestError) as caught:
        read_manifest(manifest, {}, PRESETS, STYLES)
    problems = caught.value.problems
    assert [p.split(",")[0] for p in problems] == ["row 1", "row 2", "row 3", "row 4", "row 5"], problems
    assert problems[0] == "row 1, column id: id must be text, got ['a', 'b']"
    assert "loop.wav' is a symbolic link that leads back to itself" in problems[1]
    assert problems[2].startswith("row 3, column audio:") and "the header is damaged" in problems[2]
    assert problems[3].startswith("row 4, column blend:") and "is not a Blender file" in problems[3]
    assert problems[4].startswith("row 5, column style:") and "calm" in problems[4]


@pytest.mark.parametrize("separator", ["\x85", "\u2028", "\u2029", "\x0b", "\x0c", "\x1c", "\x1d", "\x1e"])
def test_a_line_break_inside_a_cell_keeps_the_rows_and_their_numbers(project, separator):
    """Unicode's other line breaks inside a CSV cell split no row (defect 8): the id holding one
    is refused on its own row, and the rows after keep their numbers."""
    manifest = write(project / "lines.csv", f"id,audio,outputs\na{separator}b,{SPEECH},npz\nc,{SPEECH},npz\n"
                                            f"d,{SPEECH},tiff\n")
    with pytest.raises(ManifestError) as caught:
        read_manifest(manifest, {}, PRESETS, STYLES)
    problems = caught.value.problems
    assert len(problems) == 2, problems
    assert problems[0].startswith("row 2, column id:") and "line breaks" in problems[0]
    assert problems[1].startswith("row 4, column outputs: unknown output 'tiff'")


def test_a_run_hashes_each_file_once(project, monkeypatch):
    """10,000 lines of one character hash its .blend once, not once per line (defect 10)."""
    from diffsheg_core import ledger as ledger_module

    rows = "".join(f"l{i},{SPEECH if i % 2 else SPEECH2},chars/hero.blend,blend\n" for i in range(50))
    lines = read_manifest(write(project / "lines.csv", "id,audio,blend,outputs\n" + rows), {}, PRESETS, STYLES)
    hashed = []
    real = ledger_module.file_digest
    monkeypatch.setattr(ledger_module, "file_digest", lambda path, *a: hashed.append(str(path)) or real(path))
    keys = ledger_module.line_keys(lines)
    assert sorted(hashed) == sorted({str(SPEECH), str(SPEECH2), str(project / "chars" / "hero.blend")})
    monkeypatch.undo()
    assert keys == {line.id: line_key(line) for line in lines}
