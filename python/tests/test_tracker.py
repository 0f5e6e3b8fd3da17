"""The Python package against the Rust CLI on the bundled sample, and its answers to bad input."""

import threading
import time

import numpy as np
import pytest

import holoface


def test_same_landmarks_as_the_rust_cli(clip, cli_lines):
    frames = list(holoface.FrameSource(clip))
    assert len(frames) == len(cli_lines) == 6
    with holoface.FaceTracker() as tracker:
        for frame, want in zip(frames, cli_lines):
            assert frame.image.dtype == np.uint8 and frame.image.ndim == 2
            r = tracker.process(frame.image, frame.timestamp_us, frame.camera_to_world, frame.intrinsics)
            assert r.timestamp_us == want["timestamp_us"]
            assert want["face"], f"the CLI lost the face on frame {frame.index}"
            assert r.has_face and r.no_face_reason is None and len(r.faces) == 1
            face = r.face
            assert [f["id"] for f in want["faces"]] == [0]
            assert face.landmarks.dtype == np.float32 and face.landmarks.shape == (68, 2)
            diff = np.abs(face.landmarks - np.asarray(want["faces"][0]["landmarks_px"], dtype=np.float32)).max()
            assert diff <= 1e-4, f"frame {frame.index}: landmarks differ from the CLI's by {diff} px"
            assert face.raw_landmarks.dtype == np.float32 and face.raw_landmarks.shape == (68, 2)
            diff = np.abs(face.raw_landmarks - np.asarray(want["faces"][0]["raw_landmarks_px"], dtype=np.float32)).max()
            assert diff <= 1e-4, f"frame {frame.index}: raw landmarks differ from the CLI's by {diff} px"
            assert face.answered_by == want["faces"][0]["aligner"] == "krfws"
            assert face.init == want["faces"][0]["init"]
            np.testing.assert_allclose(face.camera_pose[:3, 3], want["faces"][0]["camera"]["translation_m"], atol=1e-9)
            np.testing.assert_allclose(face.world_pose[:3, 3], want["faces"][0]["world"]["position_m"], atol=1e-9)
            np.testing.assert_allclose(face.predicted_position, want["faces"][0]["world"]["predicted_position_m"], atol=1e-9)
            assert face.expression_weights == pytest.approx(want["faces"][0]["weights"], abs=1e-9)
            assert (face.smile, face.brows_raised, face.mouth_open) == tuple(
                want["faces"][0]["attributes"][k] for k in ("smile", "brows_raised", "mouth_open"))
            for pose in (face.camera_pose, face.world_pose, face.display_pose):
                assert pose.shape == (4, 4)
                np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
            assert set(r.timings) == {"prepare_ms", "align_ms", "complete_ms"}
    # The face moves right by 2 px a frame; tracking from frame 1 on follows it.
    assert [line["faces"][0]["init"] for line in cli_lines] == ["detection"] + ["tracking"] * 5


def test_read_gray_matches_the_source(clip):
    first = sorted(clip.iterdir())[0]
    img = holoface.read_gray(first)
    np.testing.assert_array_equal(img, next(iter(holoface.FrameSource(clip))).image)


def test_no_face_is_an_answer_with_a_reason():
    with holoface.FaceTracker(holoface.TrackerOptions(mode="image")) as tracker:
        r = tracker.process(np.full((240, 320), 128, np.uint8), 0)
    assert not r.has_face and r.face is None and r.faces == []
    assert r.no_face_reason == "not_detected" and r.answered_by is None


def test_the_gil_is_released_while_a_frame_runs(clip):
    image = holoface.read_gray(sorted(clip.iterdir())[0])
    tracker = holoface.FaceTracker(holoface.TrackerOptions(mode="image"))
    tracker.process(image, 0)  # warm-up
    calls = []
    done = threading.Event()

    def worker():
        for i in range(5):
            t0 = time.perf_counter()
            tracker.process(image, i)
            calls.append((t0, time.perf_counter()))
        done.set()

    ticks = []
    t = threading.Thread(target=worker)
    t.start()
    while not done.is_set():
        ticks.append(time.perf_counter())
    t.join()
    # With the GIL held through a call, this thread could not run inside it at all.
    inside = [x for a, b in calls for x in ticks if a + 0.002 < x < b - 0.002]
    assert inside, f"the main thread never ran during {len(calls)} calls of {[b - a for a, b in calls]} s"


def test_remote_without_a_server_answers_locally_and_says_why():
    opts = holoface.TrackerOptions(server="127.0.0.1:9", fingerprint="ab" * 32, deadline_ms=20)
    with holoface.FaceTracker(opts) as tracker:
        r = tracker.process(np.full((120, 160), 100, np.uint8), 1)
        assert r.link_state in ("connecting", "retrying")
        state, _failure, _message = tracker.link_status()
        assert state in ("connecting", "retrying")


@pytest.mark.parametrize(
    "image, error, words",
    [
        (np.zeros((48, 64), np.float32), TypeError, "uint8"),
        (np.zeros((48, 64, 3), np.uint8), ValueError, "shape"),
        (np.zeros((48, 64), np.uint8)[:, ::2], ValueError, "C-contiguous"),
        (np.zeros((48, 64), np.uint8).T, ValueError, "C-contiguous"),
        (np.zeros((0, 64), np.uint8), ValueError, "within"),
        ([[0, 1], [2, 3]], TypeError, "numpy array"),
        (None, TypeError, "numpy array"),
    ],
)
def test_bad_images_raise(image, error, words):
    tracker = holoface.FaceTracker()
    with pytest.raises(error, match=words):
        tracker.process(image, 0)
    # The tracker is still usable afterwards.
    assert not tracker.process(np.zeros((48, 64), np.uint8), 1).has_face


def test_bad_poses_intrinsics_and_timestamps_raise():
    tracker = holoface.FaceTracker()
    img = np.zeros((48, 64), np.uint8)
    with pytest.raises(ValueError, match="rigid"):
        tracker.process(img, 0, camera_to_world=np.full((4, 4), 2.0))
    with pytest.raises(ValueError, match="4x4"):
        tracker.process(img, 0, camera_to_world=np.eye(3))
    with pytest.raises(TypeError, match="4x4"):
        tracker.process(img, 0, camera_to_world="identity")
    with pytest.raises(ValueError, match="fx, fy > 0"):
        tracker.process(img, 0, intrinsics=(0.0, 500.0, 32.0, 24.0))
    tracker.process(img, 10, camera_to_world=np.eye(4, dtype=np.float32))
    with pytest.raises(ValueError, match="not after the previous"):
        tracker.process(img, 10)


def test_bad_options_and_assets_raise(tmp_path):
    with pytest.raises(holoface.AssetError, match=r"KRFWS model not found at .*nope.bin \(named by TrackerOptions.krfws_model\)"):
        holoface.FaceTracker(holoface.TrackerOptions(krfws_model=tmp_path / "nope.bin"))
    corrupt = tmp_path / "corrupt.bin"
    corrupt.write_bytes(b"not a model" * 10)
    with pytest.raises(holoface.AssetError, match="corrupt.bin"):
        holoface.FaceTracker(holoface.TrackerOptions(krfws_model=corrupt))
    with pytest.raises(holoface.AssetError, match="missing.onnx"):
        holoface.FaceTracker(holoface.TrackerOptions(detector_model=tmp_path / "missing.onnx"))
    with pytest.raises(ValueError, match="mode"):
        holoface.FaceTracker(holoface.TrackerOptions(mode="live"))
    with pytest.raises(ValueError, match="fingerprint is required"):
        holoface.FaceTracker(holoface.TrackerOptions(server="127.0.0.1:4433"))
    with pytest.raises(ValueError, match="ip:port"):
        holoface.FaceTracker(holoface.TrackerOptions(server="localhost", fingerprint="ab" * 32))
    with pytest.raises(ValueError, match="fingerprint"):
        holoface.FaceTracker(holoface.TrackerOptions(server="127.0.0.1:4433", fingerprint="xyz"))
    assert issubclass(holoface.AssetError, holoface.HoloFaceError)


def test_bad_files_raise_source_errors(tmp_path, clip):
    with pytest.raises(holoface.SourceError, match="nothing-here"):
        holoface.FrameSource(tmp_path / "nothing-here")
    good = sorted(clip.iterdir())[0].read_bytes()
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(good[: len(good) // 3])
    with pytest.raises(holoface.SourceError, match="truncated.png"):
        holoface.read_gray(truncated)


def _png_declaring(side):
    """A PNG whose header declares side x side grey pixels, with a token IDAT."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")


def test_an_image_over_the_size_limit_raises_before_it_is_decoded(tmp_path):
    huge = tmp_path / "huge.png"
    huge.write_bytes(_png_declaring(20000))
    with pytest.raises(holoface.SourceError, match=r"huge.png.*20000 x 20000 pixels .* image-size limit"):
        holoface.read_gray(huge)


def test_a_closed_tracker_raises():
    tracker = holoface.FaceTracker()
    tracker.close()
    with pytest.raises(ValueError, match="closed"):
        tracker.process(np.zeros((48, 64), np.uint8), 0)
    tracker.close()  # twice is fine


def test_a_y4m_stream_reads_like_the_cli(tmp_path, clip):
    frames = [holoface.read_gray(p) for p in sorted(clip.iterdir())[:3]]
    h, w = frames[0].shape
    y4m = tmp_path / "cam.y4m"
    with open(y4m, "wb") as f:
        f.write(f"YUV4MPEG2 W{w} H{h} F25:1 Ip A1:1 C420jpeg\n".encode())
        for img in frames:
            f.write(b"FRAME\n" + img.tobytes() + bytes(2 * ((w + 1) // 2) * ((h + 1) // 2)))
    got = list(holoface.FrameSource(y4m))
    assert [g.timestamp_us for g in got] == [0, 40_000, 80_000]
    for g, want in zip(got, frames):
        np.testing.assert_array_equal(g.image, want)
    y4m.write_bytes(y4m.read_bytes()[:-100])
    with pytest.raises(holoface.SourceError, match="frame 2"):
        list(holoface.FrameSource(y4m))


def test_max_faces_gives_ids_and_is_checked(clip):
    with pytest.raises(ValueError, match="max_faces"):
        holoface.FaceTracker(holoface.TrackerOptions(max_faces=0))
    frames = list(holoface.FrameSource(clip))
    with holoface.FaceTracker(holoface.TrackerOptions(max_faces=3)) as tracker:
        ids = []
        for frame in frames:
            r = tracker.process(frame.image, frame.timestamp_us, frame.camera_to_world, frame.intrinsics)
            ids.append([f.id for f in r.faces])
    assert ids == [[0]] * len(frames), "one person in the clip: one face, one id throughout"


def stub_defaults():
    """The keyword defaults of `TrackerOptions.__init__` in the type stub (python/holoface/_holoface.pyi)."""
    import ast
    import pathlib

    tree = ast.parse((pathlib.Path(__file__).parent.parent / "holoface" / "_holoface.pyi").read_text())
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "TrackerOptions")
    init = next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__")
    return {a.arg: ast.literal_eval(d) for a, d in zip(init.args.kwonlyargs, init.args.kw_defaults) if d is not None}


def test_the_detector_and_steadying_options_match_the_cli(clip):
    defaults = holoface.TrackerOptions()
    # The runtime's defaults, defined once in Rust: TrackerOptions() and the type stub both show them.
    runtime = holoface._holoface.DEFAULTS
    assert {k: getattr(defaults, k) for k in runtime} == runtime
    assert defaults.detect_tiles is None
    stub = stub_defaults()
    assert {k: stub[k] for k in runtime} == runtime, "python/holoface/_holoface.pyi shows other defaults"
    # Every option with a default is among them (the steadying ones from SteadySettings::default()).
    assert {k for k in dir(defaults) if k.startswith("steady_")} <= set(runtime)
    assert "mode" in runtime
    for bad, words in [(dict(detect_tiles=0), "detect_tiles"), (dict(detect_every=0), "detect_every"),
                       (dict(steady_shape_cutoff_hz=0.0), "steady")]:
        with pytest.raises(ValueError, match=words):
            holoface.FaceTracker(holoface.TrackerOptions(**bad))
    frames = list(holoface.FrameSource(clip))[:5]
    with holoface.FaceTracker(holoface.TrackerOptions(steady=False, detect_tiles=2)) as tracker:
        for frame in frames:
            r = tracker.process(frame.image, frame.timestamp_us, frame.camera_to_world, frame.intrinsics)
            for face in r.faces:
                assert np.array_equal(face.landmarks, face.raw_landmarks), "steady=False: landmarks are the raw ones"
                assert (face.adapt_pairs, face.adapt_corrected, face.adapt_correction) == (0, False, 0.0), \
                    "without a server nothing is adapted"


def test_faces_carry_named_blendshapes_in_zero_one(clip):
    names = holoface.BLENDSHAPE_NAMES
    assert len(names) == 39 and len(set(names)) == 39
    assert {"jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "mouthSmileLeft", "browInnerUp"} <= set(names)
    assert not any(n.startswith("eyeLook") or n in ("cheekPuff", "tongueOut") for n in names)
    frames = list(holoface.FrameSource(clip))
    with holoface.FaceTracker() as tracker:
        seen = 0
        for frame in frames:
            r = tracker.process(frame.image, frame.timestamp_us, frame.camera_to_world, frame.intrinsics)
            for face in r.faces:
                b = face.blendshapes
                assert b.dtype == np.float32 and b.shape == (39,)
                assert np.all((b >= 0.0) & (b <= 1.0)) and not np.any(np.isnan(b))
                seen += 1
    assert seen > 0


def test_the_wheel_works_outside_the_checkout(tmp_path, clip, cli_lines):
    """The wheel `make python-test` built, installed into a fresh venv in a temporary folder with its pinned
    onnxruntime, every HOLOFACE_* and ORT_* variable unset, HOME elsewhere: after install_candide, the first
    frame of the clip gives the CLI's landmarks."""
    import os
    import subprocess
    import sys

    wheel = os.environ.get("HOLOFACE_WHEEL")
    if not wheel:
        pytest.fail("HOLOFACE_WHEEL is not set: make python-test passes the wheel it built")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    # numpy at the project's pin (models/dan/requirements-eval.txt), onnxruntime at the wheel's own pin.
    subprocess.run([str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q", wheel, "numpy==2.4.6"],
                   check=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HOLOFACE_", "ORT_", "XDG_"))}
    env["HOME"] = str(tmp_path / "home")
    candide = os.path.join(os.environ.get("HOLOFACE_DATA", "../shared/data"), "candide3", "candide3.wfm")
    script = (
        "import json, sys, holoface\n"
        "try:\n"
        "    holoface.FaceTracker()\n"
        "except holoface.AssetError as e:\n"
        "    print(json.dumps({'before_install': str(e)}))\n"
        "print(json.dumps({'installed': str(holoface.install_candide(sys.argv[1]))}))\n"
        "r = holoface.FaceTracker().process(holoface.read_gray(sys.argv[2]), 0)\n"
        "print(json.dumps({'landmarks': r.face.landmarks.tolist() if r.face is not None else None}))\n"
    )
    first = sorted(clip.iterdir())[0]
    out = subprocess.run([str(py), "-c", script, os.path.abspath(candide), str(first)], cwd=tmp_path, env=env,
                         check=True, capture_output=True, text=True)
    lines = [__import__("json").loads(line) for line in out.stdout.splitlines()]
    before = lines[0]["before_install"]
    assert "CANDIDE-3 model not found" in before and "holoface.install_candide" in before, before
    assert lines[1]["installed"].startswith(str(tmp_path / "home")), lines[1]
    got = np.asarray(lines[2]["landmarks"], dtype=np.float32)
    want = np.asarray(cli_lines[0]["faces"][0]["landmarks_px"], dtype=np.float32)
    assert got.shape == (68, 2), lines
    assert np.abs(got - want).max() <= 1e-4
