// HoloFace P/Invoke binding for Unity (C#). Mirrors ffi/include/holoface.h; see ffi/unity/README.md.
// Sample code: compiled and run by no test here (no Unity or .NET on the build machine).
using System;
using System.Runtime.InteropServices;

namespace HoloFace
{
    public enum HfStatus { Ok = 0, NullPointer = 1, InvalidHandle = 2, InvalidArgument = 3, AssetError = 4, ProcessingError = 5, Panic = 6 }
    public enum HfAnsweredBy { None = 0, RemoteDan = 1, Krfws = 2, LocalDan = 3 }
    public enum HfAnchorPoint { Origin = 0, Eyes = 1, NoseBridge = 2, HeadTop = 3, Mouth = 4 }

    [StructLayout(LayoutKind.Sequential)]
    public struct HfOptions
    {
        public uint mode;                 // 0 = images, 1 = video
        public IntPtr ortDylib, detectorModel, krfwsModel, candide, server, serverFingerprint, token; // UTF-8, or IntPtr.Zero
        public uint deadlineMs;
        public float lookaheadMs;
        public byte motionCompensation;
    }

    /// <summary>Every further setting (hf_tracker_new_with), with the names and defaults of Python's
    /// TrackerOptions and the CLI's flags; structSize must be Marshal.SizeOf(HfSettings) before hf_settings_default.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct HfSettings
    {
        public uint structSize;
        public uint maxFaces;          // 1..HfFaces.MaxFaces (default 1)
        public uint detectEvery;       // default 10
        public uint detectTiles;       // 0 = automatic (1 for one face, 3 for several)
        public IntPtr cropEncoding;    // UTF-8 "raw", "png", "jpeg", "jpeg:Q", or IntPtr.Zero = "jpeg:75"
        public byte steady;            // 1 = steadied landmarks (default), 0 = raw
        public double steadyShapeCutoffHz, steadyShapeBeta, steadyRigidCutoffHz, steadyRigidBeta;
        public double steadyPreciseShapeCutoffHz, steadyPreciseShapeBeta, steadyPreciseRigidCutoffHz, steadyPreciseRigidBeta;
        public byte adapt;             // with a server: 1 = the local aligner learns each person from the server's answers (default)
    }

    [StructLayout(LayoutKind.Sequential)]
    public struct HfCamera { public double fx, fy, cx, cy; }

    [StructLayout(LayoutKind.Sequential)]
    public struct HfResult
    {
        public byte hasFace;
        public HfAnsweredBy answeredBy;
        public uint noFaceReason;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 136)] public float[] landmarksPx;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 3)] public double[] cameraTranslationM;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 4)] public double[] cameraRotationWxyz;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 3)] public double[] worldPositionM;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 4)] public double[] worldRotationWxyz;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 3)] public double[] predictedPositionM;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 3)] public double[] displayPositionM;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 4)] public double[] displayRotationWxyz;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 5)] public double[] weights;
        public byte smile, browsRaised, mouthOpen;
        /// <summary>The aligner's own landmarks, unfiltered (landmarksPx is steadied: draw that).</summary>
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 136)] public float[] rawLandmarksPx;
        /// <summary>ARKit-named blendshape coefficients in [0, 1]; Native.BlendshapeName(i) names slot i.</summary>
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = Native.Blendshapes)] public float[] blendshapes;
        /// <summary>With a server and HfSettings.adapt: pairs learnt for this face; adaptCorrected = 1 when these
        /// landmarks are the local aligner's answer corrected; adaptCorrection: the correction's size (eye distances).</summary>
        public uint adaptPairs;
        public byte adaptCorrected;
        public float adaptCorrection;
    }

    /// <summary>One face of a several-face tracker: its stable id and its answer.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct HfFace
    {
        public uint id;
        public HfResult face;
    }

    /// <summary>Every face of one frame (hf_tracker_process_faces); structSize must be Marshal.SizeOf(HfFaces).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct HfFaces
    {
        public const int MaxFaces = 8; // HF_MAX_FACES
        public uint structSize;
        public uint count;
        public uint noFaceReason;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = MaxFaces)] public HfFace[] faces;
    }

    public enum HfLinkState { Local = 0, Connecting = 1, Up = 2, Retrying = 3, Failed = 4, Stopped = 5 }
    public enum HfLinkFailure
    {
        None = 0, Unreachable = 1, Unauthorized = 2, CertificateMismatch = 3, BadVersion = 4, ServerFull = 5,
        ShuttingDown = 6, ConnectionLost = 7, Protocol = 8, Local = 9
    }

    [StructLayout(LayoutKind.Sequential)]
    public struct HfLinkStatus
    {
        public HfLinkState state;
        public HfLinkFailure failure;
        [MarshalAs(UnmanagedType.ByValArray, SizeConst = 256)] public byte[] message; // NUL-terminated UTF-8

        public string Message
        {
            get
            {
                if (message == null) return "";
                int n = Array.IndexOf(message, (byte)0);
                return System.Text.Encoding.UTF8.GetString(message, 0, n < 0 ? message.Length : n);
            }
        }
    }

    public static class Native
    {
        const string Lib = "holoface"; // libholoface.so / holoface.dll in Assets/Plugins

        [DllImport(Lib)] public static extern HfStatus hf_options_default(out HfOptions options);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_new(ref HfOptions options, out IntPtr tracker);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_process(IntPtr tracker, byte[] pixels, uint width, uint height,
            uint stride, ulong timestampUs, ref HfCamera camera, float[] worldFromCamera, out HfResult result);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_process_buf(IntPtr tracker, byte[] pixels, UIntPtr pixelsLen,
            uint width, uint height, uint stride, ulong timestampUs, ref HfCamera camera, float[] worldFromCamera, out HfResult result);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_process_faces_buf(IntPtr tracker, byte[] pixels, UIntPtr pixelsLen,
            uint width, uint height, uint stride, ulong timestampUs, ref HfCamera camera, float[] worldFromCamera, ref HfFaces faces);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_new_faces(ref HfOptions options, uint maxFaces, out IntPtr tracker);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_process_faces(IntPtr tracker, byte[] pixels, uint width, uint height,
            uint stride, ulong timestampUs, ref HfCamera camera, float[] worldFromCamera, ref HfFaces faces);
        [DllImport(Lib)] public static extern HfStatus hf_settings_default(ref HfSettings settings);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_new_with(ref HfOptions options, ref HfSettings settings, out IntPtr tracker);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_free(IntPtr tracker);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_link_status(IntPtr tracker, out HfLinkStatus status);
        [DllImport(Lib)] public static extern HfStatus hf_tracker_anchor(IntPtr tracker, ref HfResult face, uint point,
            double[] offsetM, double[] rotationDeg, [Out] float[] worldFromObject);
        [DllImport(Lib)] static extern IntPtr hf_last_error();
        [DllImport(Lib)] static extern IntPtr hf_blendshape_name(uint i);

        /// <summary>HF_BLENDSHAPES: the coefficients an HfResult carries.</summary>
        public const int Blendshapes = 39;

        /// <summary>ARKit's name of blendshape slot i ("jawOpen", "eyeBlinkLeft", ...), null past the last.</summary>
        public static string BlendshapeName(int i) => i < 0 ? null : Marshal.PtrToStringUTF8(hf_blendshape_name((uint)i));

        public static string LastError() => Marshal.PtrToStringUTF8(hf_last_error());
    }

    /// <summary>One tracker; call Process from one thread (Unity's main thread or a worker), Dispose when done.</summary>
    public sealed class FaceTracker : IDisposable
    {
        IntPtr handle;

        /// <param name="maxFaces">Faces tracked at once (1..HfFaces.MaxFaces; null: hf_settings_default's, one); read
        /// them with ProcessFaces.</param>
        /// <param name="ortDylib">The ONNX Runtime library the app ships; null: ORT_DYLIB_PATH, else the holoface
        /// data folder (the same rule for the three models below; see the README, "Installing").</param>
        /// <param name="detectorModel">face_detection_front_128x128.onnx (BlazeFace).</param>
        /// <param name="krfwsModel">krfws.bin (the local aligner).</param>
        /// <param name="candide">The CANDIDE-3 .wfm (head pose and expressions).</param>
        /// <param name="configure">Changes the further settings (detector, crop encoding, landmark filter) after
        /// hf_settings_default filled them; a maxFaces given above is set after it.</param>
        /// <param name="cropEncoding">Crop encoding on the wire ("raw", "png", "jpeg", "jpeg:Q"); null: "jpeg:75".</param>
        public FaceTracker(string server = null, string fingerprint = null, string token = null, uint? maxFaces = null,
            string ortDylib = null, string detectorModel = null, string krfwsModel = null, string candide = null,
            Func<HfSettings, HfSettings> configure = null, string cropEncoding = null)
        {
            Native.hf_options_default(out var o);
            var settings = new HfSettings { structSize = (uint)Marshal.SizeOf(typeof(HfSettings)) };
            var d = Native.hf_settings_default(ref settings);
            if (d != HfStatus.Ok) throw new InvalidOperationException($"HoloFace: {d}: {Native.LastError()}");
            if (configure != null) settings = configure(settings);
            if (maxFaces.HasValue) settings.maxFaces = maxFaces.Value;
            var strings = new[] { server, fingerprint, token, ortDylib, detectorModel, krfwsModel, candide, cropEncoding };
            var ptrs = new IntPtr[strings.Length];
            try
            {
                for (int i = 0; i < strings.Length; i++) ptrs[i] = strings[i] == null ? IntPtr.Zero : Marshal.StringToCoTaskMemUTF8(strings[i]);
                o.server = ptrs[0]; o.serverFingerprint = ptrs[1]; o.token = ptrs[2];
                o.ortDylib = ptrs[3]; o.detectorModel = ptrs[4]; o.krfwsModel = ptrs[5]; o.candide = ptrs[6];
                settings.cropEncoding = ptrs[7];
                var s = Native.hf_tracker_new_with(ref o, ref settings, out handle);
                if (s != HfStatus.Ok) throw new InvalidOperationException($"HoloFace: {s}: {Native.LastError()}");
            }
            finally
            {
                foreach (var p in ptrs) if (p != IntPtr.Zero) Marshal.FreeCoTaskMem(p);
            }
        }

        /// <param name="worldFromCamera">Row-major 4x4 camera-to-world matrix (e.g. from the headset's locatable camera).</param>
        public HfResult Process(byte[] gray, int width, int height, ulong timestampUs, HfCamera camera, float[] worldFromCamera)
        {
            CheckFrame(gray, width, height, worldFromCamera);
            // The length too: the library refuses a buffer shorter than the image instead of reading past it.
            var s = Native.hf_tracker_process_buf(handle, gray, (UIntPtr)gray.Length, (uint)width, (uint)height, (uint)width,
                timestampUs, ref camera, worldFromCamera, out var r);
            if (s != HfStatus.Ok) throw new InvalidOperationException($"HoloFace: {s}: {Native.LastError()}");
            return r;
        }

        /// <summary>Every face of the frame, oldest track first, each with its stable id (empty: no face).</summary>
        public HfFace[] ProcessFaces(byte[] gray, int width, int height, ulong timestampUs, HfCamera camera, float[] worldFromCamera)
        {
            CheckFrame(gray, width, height, worldFromCamera);
            var all = new HfFaces { structSize = (uint)Marshal.SizeOf(typeof(HfFaces)), faces = new HfFace[HfFaces.MaxFaces] };
            var s = Native.hf_tracker_process_faces_buf(handle, gray, (UIntPtr)gray.Length, (uint)width, (uint)height,
                (uint)width, timestampUs, ref camera, worldFromCamera, ref all);
            if (s != HfStatus.Ok) throw new InvalidOperationException($"HoloFace: {s}: {Native.LastError()}");
            var faces = new HfFace[Math.Min(all.count, (uint)HfFaces.MaxFaces)];
            Array.Copy(all.faces, faces, faces.Length);
            return faces;
        }

        // The C API reads width * height bytes and 16 floats: check here, where the array lengths are known.
        void CheckFrame(byte[] gray, int width, int height, float[] worldFromCamera)
        {
            if (handle == IntPtr.Zero) throw new ObjectDisposedException(nameof(FaceTracker));
            if (gray == null) throw new ArgumentNullException(nameof(gray));
            if (width <= 0 || height <= 0 || (long)width * height > gray.Length)
                throw new ArgumentException($"image {width}x{height} needs {(long)width * height} bytes, got {gray.Length}", nameof(gray));
            if (worldFromCamera != null && worldFromCamera.Length != 16)
                throw new ArgumentException($"worldFromCamera needs 16 floats (row-major 4x4), got {worldFromCamera.Length}", nameof(worldFromCamera));
        }

        /// <summary>The link to the alignment server: Local without a server; Retrying/Failed say why frames are
        /// answered on the headset (wrong token, certificate mismatch, unreachable...).</summary>
        public HfLinkStatus LinkStatus()
        {
            if (handle == IntPtr.Zero) throw new ObjectDisposedException(nameof(FaceTracker));
            var s = Native.hf_tracker_link_status(handle, out var st);
            if (s != HfStatus.Ok) throw new InvalidOperationException($"HoloFace: {s}: {Native.LastError()}");
            return st;
        }

        /// <summary>Where an object anchored on the face sits in the world: the face's display pose after the
        /// anchor (a head point, an offset in metres and a rotation in degrees about the head's x, y, z; head
        /// frame: x right, y down, z into the head), as a row-major 4x4 object-to-world matrix in the frame of
        /// the camera-to-world poses passed in. The same anchors as the tools' scene files
        /// (tools/assets/augment/glasses-and-hat.toml).</summary>
        public float[] Anchor(HfResult face, HfAnchorPoint point, double[] offsetM, double[] rotationDeg)
        {
            if (handle == IntPtr.Zero) throw new ObjectDisposedException(nameof(FaceTracker));
            if (offsetM == null || offsetM.Length != 3) throw new ArgumentException("offsetM needs 3 doubles", nameof(offsetM));
            if (rotationDeg == null || rotationDeg.Length != 3) throw new ArgumentException("rotationDeg needs 3 doubles", nameof(rotationDeg));
            var m = new float[16];
            var s = Native.hf_tracker_anchor(handle, ref face, (uint)point, offsetM, rotationDeg, m);
            if (s != HfStatus.Ok) throw new InvalidOperationException($"HoloFace: {s}: {Native.LastError()}");
            return m;
        }

        public void Dispose()
        {
            if (handle != IntPtr.Zero) { Native.hf_tracker_free(handle); handle = IntPtr.Zero; }
        }
    }
}
