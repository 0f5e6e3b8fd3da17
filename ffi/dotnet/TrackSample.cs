// Console check of the Unity binding (ffi/unity/HoloFace.cs, compiled unchanged next to this file) against
// libholoface: tracks the face of a gray PGM over 30 video frames, then checks that a bad handle, a disposed
// tracker, a short pixel buffer and an old timestamp are errors with a message, never a crash.
//
//   mcs -out:track.exe ffi/unity/HoloFace.cs ffi/dotnet/TrackSample.cs && LD_LIBRARY_PATH=target/debug mono track.exe face.pgm
//
// Asset paths come from the environment (ORT_DYLIB_PATH, HOLOFACE_DETECTOR_MODEL, ...), as for the C example,
// except where a check passes one to the FaceTracker constructor, as an app that ships its assets does.
// Exit status 0 = every check passed.
using System;
using System.IO;
using System.Text;
using HoloFace;

static class TrackSample
{
    static int failures;

    static void Check(bool ok, string what)
    {
        Console.WriteLine((ok ? "ok   " : "FAIL ") + what);
        if (!ok) failures++;
    }

    static void Expect<T>(string what, Action action, string words) where T : Exception
    {
        try
        {
            action();
            Check(false, what + ": no exception");
        }
        catch (T e)
        {
            Check(e.Message.Contains(words), what + ": " + e.GetType().Name + ": " + e.Message);
        }
    }

    static byte[] ReadPgm(string path, out int width, out int height)
    {
        var bytes = File.ReadAllBytes(path);
        // Header: "P5", width, height, maxval, each separated by whitespace, then one whitespace byte.
        var fields = new string[4];
        int pos = 0;
        for (int f = 0; f < 4; f++)
        {
            while (pos < bytes.Length && char.IsWhiteSpace((char)bytes[pos])) pos++;
            int start = pos;
            while (pos < bytes.Length && !char.IsWhiteSpace((char)bytes[pos])) pos++;
            fields[f] = Encoding.ASCII.GetString(bytes, start, pos - start);
        }
        pos++;
        if (fields[0] != "P5" || fields[3] != "255") throw new InvalidDataException(path + ": not a binary 8-bit PGM");
        width = int.Parse(fields[1]);
        height = int.Parse(fields[2]);
        if (bytes.Length - pos < width * height) throw new InvalidDataException(path + ": truncated");
        var px = new byte[width * height];
        Array.Copy(bytes, pos, px, 0, px.Length);
        return px;
    }

    static int Main(string[] args)
    {
        if (args.Length != 1)
        {
            Console.Error.WriteLine("usage: mono track.exe face.pgm");
            return 2;
        }
        int w, h;
        var px = ReadPgm(args[0], out w, out h);
        Console.WriteLine("image " + w + "x" + h);
        var cam = new HfCamera { fx = 500, fy = 500, cx = w / 2.0, cy = h / 2.0 };
        var pose = new float[] { 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1 };

        // A handle that is not one of ours is rejected by the library, with a message.
        HfResult r;
        var s = Native.hf_tracker_process(new IntPtr(0x1000), px, (uint)w, (uint)h, (uint)w, 0, ref cam, pose, out r);
        Check(s == HfStatus.InvalidHandle, "foreign handle: " + s + ": " + Native.LastError());
        s = Native.hf_tracker_free(new IntPtr(0x1000));
        Check(s == HfStatus.InvalidHandle, "free of a foreign handle: " + s);

        int faces = 0;
        var tracker = new FaceTracker();
        for (int i = 0; i < 30; i++)
        {
            r = tracker.Process(px, w, h, (ulong)i * 33333, cam, pose);
            if (r.hasFace == 1) faces++;
            if (i % 10 == 0 || i == 29)
                Console.WriteLine(string.Format("frame {0,2} face={1} by={2} nose(px)=({3:F1}, {4:F1}) head(m)=({5:F3}, {6:F3}, {7:F3})",
                    i, r.hasFace, r.answeredBy, r.landmarksPx[60], r.landmarksPx[61],
                    r.worldPositionM[0], r.worldPositionM[1], r.worldPositionM[2]));
        }
        Check(faces >= 25, faces + " of 30 frames with a face");
        // The last field of HfResult: the aligner's own landmarks beside the steadied ones (a still photo:
        // both on the same nose, within a few pixels), so the marshalled layout matches the library's.
        Check(r.hasFace == 1 && r.rawLandmarksPx.Length == 136 && r.rawLandmarksPx[60] > 0
              && Math.Abs(r.rawLandmarksPx[60] - r.landmarksPx[60]) < 5 && Math.Abs(r.rawLandmarksPx[61] - r.landmarksPx[61]) < 5,
              "raw nose (" + r.rawLandmarksPx[60] + ", " + r.rawLandmarksPx[61] + ") vs steadied (" + r.landmarksPx[60] + ", " + r.landmarksPx[61] + ")");
        // The shipped scene's anchors through the C ABI (tools/assets/augment/glasses-and-hat.toml): the glasses
        // 18 mm in front of the eyes, the hat's brim above the forehead; both near the head, the hat above it
        // (world -y is up for the identity camera pose), and the glasses' rotation the head's own.
        var glasses = tracker.Anchor(r, HfAnchorPoint.Eyes, new[] { 0.0, 0.002, -0.018 }, new[] { 0.0, 0.0, 0.0 });
        var hat = tracker.Anchor(r, HfAnchorPoint.HeadTop, new[] { 0.0, 0.025, 0.06 }, new[] { -8.0, 0.0, 0.0 });
        var head = r.displayPositionM;
        Func<float[], double> Dist = m => Math.Sqrt(Math.Pow(m[3] - head[0], 2) + Math.Pow(m[7] - head[1], 2)
                                                    + Math.Pow(m[11] - head[2], 2));
        Console.WriteLine(string.Format("glasses at ({0:F3}, {1:F3}, {2:F3}) m, hat at ({3:F3}, {4:F3}, {5:F3}) m",
            glasses[3], glasses[7], glasses[11], hat[3], hat[7], hat[11]));
        Check(Dist(glasses) < 0.05 && Dist(hat) > 0.05 && Dist(hat) < 0.2 && hat[7] < glasses[7] && glasses[15] == 1,
              "anchored glasses " + Dist(glasses).ToString("F3") + " m and hat " + Dist(hat).ToString("F3") + " m from the head");
        Expect<InvalidOperationException>("anchor at an unknown point", () => tracker.Anchor(r, (HfAnchorPoint)9,
            new[] { 0.0, 0.0, 0.0 }, new[] { 0.0, 0.0, 0.0 }), "point 9");
        var link = tracker.LinkStatus();
        Check(link.state == HfLinkState.Local && link.failure == HfLinkFailure.None, "link state without a server: " + link.state);

        Expect<InvalidOperationException>("old timestamp", () => tracker.Process(px, w, h, 0, cam, pose), "not after the previous");
        Expect<ArgumentException>("short pixel buffer", () => tracker.Process(new byte[10], w, h, 10000000, cam, pose), "needs");
        Expect<ArgumentException>("3x3 pose", () => tracker.Process(px, w, h, 10000000, cam, new float[9]), "16 floats");
        Expect<InvalidOperationException>("non-rigid pose",
            () => tracker.Process(px, w, h, 10000000, cam, new float[16]), "rigid");
        var badCam = new HfCamera { fx = 0, fy = 500, cx = 1, cy = 1 };
        Expect<InvalidOperationException>("zero focal length", () => tracker.Process(px, w, h, 20000000, badCam, pose), "fx, fy > 0");
        // The tracker still works after those errors.
        r = tracker.Process(px, w, h, 30000000, cam, pose);
        Check(r.hasFace == 1, "a frame after the errors has a face");

        tracker.Dispose();
        tracker.Dispose(); // twice is fine
        Expect<ObjectDisposedException>("disposed tracker", () => tracker.Process(px, w, h, 40000000, cam, pose), "FaceTracker");
        Expect<ObjectDisposedException>("disposed tracker's link", () => tracker.LinkStatus(), "FaceTracker");

        // Several faces: one person in the picture, so one face with id 0 in every frame.
        Expect<InvalidOperationException>("maxFaces 0", () => { using (new FaceTracker(maxFaces: 0)) { } }, "max_faces");
        using (var multi = new FaceTracker(maxFaces: 3))
        {
            int withId0 = 0;
            for (int i = 0; i < 30; i++)
            {
                var all = multi.ProcessFaces(px, w, h, (ulong)i * 33333, cam, pose);
                if (all.Length == 1 && all[0].id == 0 && all[0].face.hasFace == 1) withId0++;
            }
            Check(withId0 >= 25, "several-face tracker: " + withId0 + " of 30 frames with exactly face #0");
        }

        // Every further setting, as in Python and the CLI: the landmark filter off gives the raw landmarks.
        Expect<InvalidOperationException>("detectTiles 99", () =>
        {
            using (new FaceTracker(configure: st => { st.detectTiles = 99; return st; })) { }
        }, "detect_tiles");
        Expect<InvalidOperationException>("a crop encoding that does not exist", () =>
        {
            using (new FaceTracker(cropEncoding: "webp")) { }
        }, "crop_encoding");
        using (var raw = new FaceTracker(configure: st => { st.steady = 0; st.detectTiles = 2; return st; }))
        {
            int same = 0;
            for (int i = 0; i < 10; i++)
            {
                var f = raw.Process(px, w, h, (ulong)i * 33333, cam, pose);
                bool equal = f.hasFace == 1;
                for (int k = 0; equal && k < 136; k++) equal = f.landmarksPx[k] == f.rawLandmarksPx[k];
                if (equal) same++;
            }
            Check(same >= 8, "steady = 0: " + same + " of 10 frames with landmarks equal to the raw ones");
            var last = raw.Process(px, w, h, 10 * 33333, cam, pose);
            bool bounded = last.blendshapes != null && last.blendshapes.Length == Native.Blendshapes;
            for (int k = 0; bounded && k < Native.Blendshapes; k++)
                bounded = last.blendshapes[k] >= 0f && last.blendshapes[k] <= 1f && Native.BlendshapeName(k) != null;
            Check(bounded && Native.BlendshapeName(Native.Blendshapes) == null && Native.BlendshapeName(15) == "jawOpen",
                "blendshapes: " + Native.Blendshapes + " named coefficients in [0, 1]");
            // The struct's tail: without a server nothing is adapted.
            Check(last.adaptPairs == 0 && last.adaptCorrected == 0 && last.adaptCorrection == 0f,
                "no server: no adaptation (" + last.adaptPairs + " pairs)");
        }
        // The binding types no default of its own: what a tracker starts from is the C ABI's (which the C ABI's
        // own test compares with the facade's), field by field.
        var seen = new HfSettings();
        using (new FaceTracker(configure: st => { seen = st; return st; })) { }
        var want = new HfSettings { structSize = (uint)System.Runtime.InteropServices.Marshal.SizeOf(typeof(HfSettings)) };
        Check(Native.hf_settings_default(ref want) == HfStatus.Ok, "hf_settings_default");
        Check(seen.maxFaces == want.maxFaces && seen.detectEvery == want.detectEvery && seen.detectTiles == want.detectTiles
            && seen.cropEncoding == want.cropEncoding && seen.steady == want.steady
            && seen.steadyShapeCutoffHz == want.steadyShapeCutoffHz && seen.steadyShapeBeta == want.steadyShapeBeta
            && seen.steadyRigidCutoffHz == want.steadyRigidCutoffHz && seen.steadyRigidBeta == want.steadyRigidBeta
            && seen.steadyPreciseShapeCutoffHz == want.steadyPreciseShapeCutoffHz
            && seen.steadyPreciseShapeBeta == want.steadyPreciseShapeBeta
            && seen.steadyPreciseRigidCutoffHz == want.steadyPreciseRigidCutoffHz
            && seen.steadyPreciseRigidBeta == want.steadyPreciseRigidBeta && seen.adapt == want.adapt,
            "the C# defaults are hf_settings_default's, field by field (maxFaces " + seen.maxFaces + ", adapt " + seen.adapt + ")");
        Check(want.adapt == 1 && want.maxFaces == 1, "HfSettings defaults: the adaptation on, one face");

        // A path the app passes wins over the environment; a missing one names the asset, the path and why.
        Expect<InvalidOperationException>("missing model file (passed by the app)", () =>
        {
            using (new FaceTracker(krfwsModel: "/nonexistent/app/krfws.bin")) { }
        }, "KRFWS model not found at /nonexistent/app/krfws.bin (the path given");
        Expect<InvalidOperationException>("missing model file (environment)", () =>
        {
            Environment.SetEnvironmentVariable("HOLOFACE_KRFWS_MODEL", "/nonexistent/krfws.bin");
            using (new FaceTracker()) { }
        }, "KRFWS model not found at /nonexistent/krfws.bin (named by $HOLOFACE_KRFWS_MODEL)");

        Console.WriteLine(failures == 0 ? "all checks passed" : failures + " checks failed");
        return failures == 0 ? 0 : 1;
    }
}
