//! The real alignment server (real ONNX Runtime, real DAN model) on loopback,
//! with a well-behaved client next to misbehaving ones.
//!
//! Needs the model (`$HOLOFACE_DAN_MODEL` or `models/assets/dan.onnx`) and
//! ONNX Runtime (`$ORT_DYLIB_PATH`, `.cache/holoface/` or `.venv`): the
//! tests fail, they do not skip, when either is missing.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::time::Duration;

use bytes::Bytes;
use holoface_alignment_server::config::Settings;
use holoface_inference::{
    BatchTensor, CascadeEngine, InferenceEngine, LandmarkOut, LoadedCascade, OnnxEngine,
};
use holoface_protocol::{
    CloseCode, CropEncoding, DropReason, FrameReply, Message, PROTOCOL_VERSION, ReplyChannel, ReplyOutcome,
};
use holoface_tests::{
    RunningServer, TEST_TOKEN, TestClient, WAIT, client_endpoint, connect_raw, frame, hello,
    loopback_settings, model_path, ort_dylib_path, refiner_path, refused_with, send_frame_on, within,
    write_framed,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Generous: the untrained DAN takes tens of ms per crop on a loaded 2-core box.
const DEADLINE_MS: u16 = 3_000;

fn settings() -> Settings {
    let mut s = loopback_settings();
    s.max_frame_age = Duration::from_millis(u64::from(DEADLINE_MS));
    s
}

/// Landmarks the server's pipeline (DAN, then the refinement cascade) computes for the same crop, run
/// directly.
fn reference(seed: u8) -> LandmarkOut {
    let s = loopback_settings();
    let mut opts = s.engine.clone();
    opts.max_batch = 1;
    let refiner = LoadedCascade::load(&refiner_path()).unwrap();
    let mut engine = CascadeEngine::new(OnnxEngine::load(&opts).unwrap(), refiner).unwrap();
    let mut batch = BatchTensor::new(1, 112 * 112);
    batch.push(&frame(0, seed, 0).crop.data).unwrap();
    let mut out = vec![LandmarkOut::default()];
    engine.infer(&batch, &mut out).unwrap();
    out.remove(0)
}

fn assert_landmarks(reply: &FrameReply, expected: &LandmarkOut) {
    let ReplyOutcome::Landmarks {
        landmarks, face_prob, ..
    } = &reply.outcome
    else {
        panic!("frame {} was not aligned: {:?}", reply.frame_id, reply.outcome)
    };
    assert_eq!(landmarks.len(), 68);
    assert!((0.0..=1.0).contains(face_prob), "face_prob {face_prob}");
    assert!(
        (face_prob - expected.face_prob).abs() < 1e-3,
        "face_prob {face_prob} vs {}",
        expected.face_prob
    );
    for (got, want) in landmarks.iter().zip(&expected.landmarks) {
        assert!(
            (got[0] - want[0]).abs() < 1e-2 && (got[1] - want[1]).abs() < 1e-2,
            "landmark {got:?} vs {want:?}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn good_client_gets_correct_landmarks_and_welcome_from_model_metadata() {
    let expected = reference(3);
    let server = RunningServer::start(settings()).await.unwrap();
    let mut client = within(
        "connect",
        TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN)),
    )
    .await
    .unwrap();
    let w = &client.welcome;
    assert_eq!(w.version, PROTOCOL_VERSION);
    assert_eq!((w.landmark_count, w.crop_size), (68, 112));
    assert_eq!(w.mean_shape.len(), 68);
    assert_eq!(w.encoding, CropEncoding::Raw);
    assert_eq!(w.reply_channel, ReplyChannel::Datagram);
    assert_eq!(w.max_in_flight, 2);
    for id in 1..=3 {
        let reply = within("reply", client.request(&frame(id, 3, DEADLINE_MS)))
            .await
            .unwrap();
        assert_eq!(reply.frame_id, id);
        assert_landmarks(&reply, &expected);
    }
    assert_eq!(
        server
            .metrics
            .frames_aligned
            .load(std::sync::atomic::Ordering::Relaxed),
        3
    );
    server.shutdown().await.unwrap();
}

/// What a headset gets from the server is what `holoface eval --aligner remote` measures: a validation
/// face's crop, JPEG q75 as the client sends it, answered by the server (DAN, then the refinement
/// cascade) and by the eval's in-process remote aligner, gives the same landmarks; and the refinement
/// did move them away from DAN's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_servers_answer_is_what_eval_remote_measures() {
    use holoface_harness::data::{Split, default_data_root, load_folder};
    use holoface_models::crop::{Crop112, crop_bilinear};
    use holoface_models::geometry::{Point2, Rect};
    use holoface_models::shape::{dan_mean_shape, fit_to_box};
    use holoface_runtime::align::{Aligner, crop_from_image, landmarks_from_crop};
    use holoface_runtime::link::CropCodec;

    let faces = load_folder(
        &default_data_root().join("faces68/train"),
        Split::Validation,
        true,
    )
    .unwrap();
    let face = &faces[0];
    let gt = face.landmarks.unwrap();
    let mean = dan_mean_shape();
    let mut init = [Point2::default(); 68];
    fit_to_box(&mean, &Rect::bounding(&gt).unwrap(), &mut init);
    let engine = holoface_inference::OnnxOptions {
        model: model_path(),
        ort_dylib: ort_dylib_path(),
        intra_threads: 1,
        max_batch: 1,
        provider: holoface_inference::Provider::Cpu,
        spin: false,
    };
    let mut remote = holoface_harness::dan_aligner::server_pipeline(&engine, &refiner_path()).unwrap();
    let eval = remote.align(&face.image.view(), &init).unwrap();
    let mut dan_alone = holoface_harness::dan_aligner::dan_alone(&engine).unwrap();
    dan_alone.set_wire_codec(Some(CropCodec::default()));
    let dan = dan_alone.align(&face.image.view(), &init).unwrap();
    assert!(eval.accepted, "a validation face is accepted");

    // The same crop, as the client builds and sends it.
    let sim = crop_from_image(&init, &mean).unwrap();
    let mut crop = Crop112::default();
    crop_bilinear(&face.image.view(), &sim, &mut crop).unwrap();
    let server = RunningServer::start(settings()).await.unwrap();
    let mut h = hello(TEST_TOKEN);
    h.encodings = vec![CropEncoding::Jpeg];
    let mut client = within("connect", TestClient::connect(server.addr, server.fingerprint, h))
        .await
        .unwrap();
    let mut req = frame(1, 0, DEADLINE_MS);
    req.crop = holoface_runtime::crop_codec::encode(CropCodec::default(), crop.as_slice(), 112, 112).unwrap();
    let reply = within("reply", client.request(&req)).await.unwrap();
    let ReplyOutcome::Landmarks {
        landmarks, face_prob, ..
    } = &reply.outcome
    else {
        panic!("not aligned: {:?}", reply.outcome)
    };
    let served = landmarks_from_crop(landmarks, *face_prob, &sim, 0.5).unwrap();
    let mut moved = 0.0f32;
    for ((s, e), d) in served.landmarks.iter().zip(&eval.landmarks).zip(&dan.landmarks) {
        assert!(s.dist(*e) < 1e-3, "server {s:?} vs eval --aligner remote {e:?}");
        moved = moved.max(s.dist(*d));
    }
    assert!(
        moved > 0.1,
        "refinement moved no landmark by more than {moved} px"
    );
    let text = server.metrics.render();
    assert!(text.contains("refiner=\"holoface-ert "), "{text}");
    assert!(text.contains("holoface_refine_seconds_count 1"), "{text}");
    server.shutdown().await.unwrap();
}

/// A refiner model that is missing, damaged or not a refiner stops the start with an error naming the file
/// and the setting; `refine.enabled = false` serves DAN alone.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_missing_or_corrupt_refiner_model_is_a_clear_start_up_error() {
    let dir = std::env::temp_dir().join(format!("holoface-e2e-refiner-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut corrupt = std::fs::read(refiner_path()).unwrap();
    corrupt.truncate(corrupt.len() / 2);
    std::fs::write(dir.join("half.bin"), &corrupt).unwrap();
    std::fs::write(dir.join("text.bin"), b"not a model").unwrap();
    for (file, expect) in [
        ("missing.bin", "not found at"),
        ("half.bin", "checksum"),
        ("text.bin", "not this kind of file"),
    ] {
        let mut s = settings();
        s.refine_model = Some(dir.join(file));
        let e = holoface_alignment_server::AlignmentServer::bind(s)
            .await
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(file) && e.contains(expect) && e.contains("refine.model"),
            "{file}: {e}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
    let mut off = settings();
    off.refine_model = None;
    let server = RunningServer::start(off).await.unwrap();
    let info = server.metrics.render();
    assert!(info.contains("refiner=\"none\""), "{info}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_version_1_client_is_served_at_version_1() {
    let expected = reference(4);
    let server = RunningServer::start(settings()).await.unwrap();
    let mut old = hello(TEST_TOKEN);
    old.version = 1;
    let mut client = within(
        "connect v1",
        TestClient::connect(server.addr, server.fingerprint, old),
    )
    .await
    .unwrap();
    assert_eq!(
        client.welcome.version, 1,
        "the welcome says which version serves it"
    );
    let reply = within("v1 reply", client.request(&frame(1, 4, DEADLINE_MS)))
        .await
        .unwrap();
    assert_landmarks(&reply, &expected);
    server.shutdown().await.unwrap();
}

/// A headset with three faces sends one crop per face for the same camera frame, each under its track
/// id: each reply carries its track and that crop's landmarks, and a newer frame of one face does not
/// drop another face's crop (the server orders frames per track).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_faces_of_one_frame_are_answered_per_track() {
    let server = RunningServer::start(settings()).await.unwrap();
    let mut h = hello(TEST_TOKEN);
    h.max_in_flight = 6;
    let mut client = within("connect", TestClient::connect(server.addr, server.fingerprint, h))
        .await
        .unwrap();
    assert_eq!(
        client.welcome.max_in_flight, 6,
        "granted up to the server's limit (8)"
    );
    let seeds = [(1_u16, 11_u8), (2, 12), (3, 13)];
    for frame_id in [40_u64, 41] {
        for (track, seed) in seeds {
            let mut f = frame(frame_id, seed, DEADLINE_MS);
            f.track_id = track;
            within("send", client.send_frame(&f)).await.unwrap();
        }
        let mut got = Vec::new();
        for _ in 0..seeds.len() {
            got.push(within("reply", client.next_reply()).await.unwrap());
        }
        got.sort_by_key(|r| r.track_id);
        for (reply, (track, seed)) in got.iter().zip(seeds) {
            assert_eq!((reply.frame_id, reply.track_id), (frame_id, track));
            assert_landmarks(reply, &reference(seed));
        }
    }
    // The same frame id on the same track again is still a duplicate.
    let mut f = frame(41, 11, DEADLINE_MS);
    f.track_id = 1;
    let _ = client.send_frame(&f).await;
    assert_eq!(
        within("close", client.close_code()).await,
        Some(CloseCode::ProtocolViolation)
    );
    server.shutdown().await.unwrap();
}

/// A client that said version 2 in its hello cannot send a track id (it would be served as one face).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_track_id_from_a_version_2_client_is_a_protocol_violation() {
    let server = RunningServer::start(settings()).await.unwrap();
    let mut old = hello(TEST_TOKEN);
    old.version = 2;
    let mut client = within(
        "connect v2",
        TestClient::connect(server.addr, server.fingerprint, old),
    )
    .await
    .unwrap();
    let reply = within("track 0 is served", client.request(&frame(1, 4, DEADLINE_MS)))
        .await
        .unwrap();
    assert_landmarks(&reply, &reference(4));
    let mut f = frame(2, 4, DEADLINE_MS);
    f.track_id = 3;
    let _ = client.send_frame(&f).await;
    assert_eq!(
        within("close", client.close_code()).await,
        Some(CloseCode::ProtocolViolation)
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replies_on_a_stream_when_configured() {
    let expected = reference(5);
    let mut s = settings();
    s.reply_channel = ReplyChannel::Stream;
    let server = RunningServer::start(s).await.unwrap();
    let mut client = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    assert_eq!(client.welcome.reply_channel, ReplyChannel::Stream);
    for id in [10, 11] {
        let reply = within("stream reply", client.request(&frame(id, 5, DEADLINE_MS)))
            .await
            .unwrap();
        assert_landmarks(&reply, &expected);
    }
    server.shutdown().await.unwrap();
}

/// A server whose handshake stream ends a moment before its close code arrives (ours dropped the stream
/// first): the client still reports the refusal, so a wrong token is a permanent failure, not a retryable
/// "stream ended" (found by the container smoke test, `make image-test`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refusal_whose_stream_ends_before_the_close_is_still_the_refusal() {
    use holoface_runtime::link::FailureKind;
    let id = holoface_alignment_server::tls::ServerIdentity::self_signed(&["localhost".to_owned()]).unwrap();
    let config = quinn::ServerConfig::with_crypto(id.quic_server_config().unwrap());
    let endpoint = quinn::Endpoint::server(config, "127.0.0.1:0".parse().unwrap()).unwrap();
    let addr = endpoint.local_addr().unwrap();
    let refuser = tokio::spawn(async move {
        let conn = endpoint.accept().await.unwrap().await.unwrap();
        let (mut send, _recv) = conn.accept_bi().await.unwrap();
        send.finish().unwrap();
        // The scenario itself: the stream's end reaches the client well before the close (not a wait for
        // something; the client's report is checked whatever the gap).
        tokio::time::sleep(Duration::from_millis(100)).await;
        conn.close(CloseCode::Unauthorized.as_u32().into(), b"token rejected");
        endpoint.wait_idle().await;
    });
    let err = within(
        "the refusal",
        TestClient::connect(addr, id.fingerprint, hello("wrong")),
    )
    .await
    .unwrap_err();
    assert_eq!(err.kind(), FailureKind::Unauthorized, "{err}");
    assert!(err.kind().is_permanent());
    within("the refusing server", refuser).await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn handshake_failures_get_their_close_codes_before_inference() {
    let server = RunningServer::start(settings()).await.unwrap();
    let (addr, fp) = (server.addr, server.fingerprint);
    let mut wrong_version = hello(TEST_TOKEN);
    wrong_version.version = PROTOCOL_VERSION + 1;
    assert_eq!(
        within("bad version", refused_with(addr, fp, wrong_version)).await,
        Some(CloseCode::BadVersion)
    );
    assert_eq!(
        within("bad token", refused_with(addr, fp, hello("wrong"))).await,
        Some(CloseCode::Unauthorized)
    );
    // A frame request where the hello should be.
    let endpoint = client_endpoint(fp).unwrap();
    let conn = connect_raw(&endpoint, addr).await.unwrap();
    let (mut send, _recv) = conn.open_bi().await.unwrap();
    write_framed(&mut send, &Message::FrameRequest(frame(1, 0, 10)))
        .await
        .unwrap();
    let code = holoface_tests::app_close_code(&within("out of order", conn.closed()).await);
    assert_eq!(code, Some(CloseCode::ProtocolViolation));

    let m = &server.metrics;
    use std::sync::atomic::Ordering::Relaxed;
    assert_eq!(m.auth_bad_version.load(Relaxed), 1);
    assert_eq!(m.auth_unauthorized.load(Relaxed), 1);
    assert_eq!(
        m.frames_received.load(Relaxed),
        0,
        "no frame was read from unauthenticated clients"
    );
    assert_eq!(m.batch_size.count(), 0, "no inference was spent on them");
    server.shutdown().await.unwrap();
}

/// Runs a misbehaving client to its close code while a good client keeps
/// getting landmarks.
async fn misbehaviour_next_to_good_client<F, Fut>(name: &str, expected: CloseCode, misbehave: F)
where
    F: FnOnce(TestClient) -> Fut,
    Fut: Future<Output = Option<CloseCode>> + Send + 'static,
{
    let reference = reference(9);
    let server = RunningServer::start(settings()).await.unwrap();
    let mut good = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    let bad = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    let bad_task = tokio::spawn(misbehave(bad));
    for id in 1..=4 {
        let reply = within("good reply", good.request(&frame(id, 9, DEADLINE_MS)))
            .await
            .unwrap();
        assert_landmarks(&reply, &reference);
    }
    let code = within(name, bad_task).await.unwrap();
    assert_eq!(code, Some(expected), "{name}");
    // And after it is gone.
    let reply = within("good reply after", good.request(&frame(100, 9, DEADLINE_MS)))
        .await
        .unwrap();
    assert_landmarks(&reply, &reference);
    assert_eq!(
        server.metrics.closes_for(expected),
        1,
        "{name}: close counted once"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_frame_stream_is_closed_malformed() {
    misbehaviour_next_to_good_client("malformed", CloseCode::Malformed, |bad| async move {
        let _ = bad.send_stream_bytes(&[0x03, 0xde, 0xad, 0xbe, 0xef]).await;
        bad.close_code().await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversize_frame_stream_is_closed_too_large() {
    misbehaviour_next_to_good_client("oversize", CloseCode::TooLarge, |bad| async move {
        let _ = bad.send_stream_bytes(&vec![0x03; 200 * 1024]).await;
        bad.close_code().await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversize_length_prefix_is_closed_too_large() {
    misbehaviour_next_to_good_client("huge crop length", CloseCode::TooLarge, |bad| async move {
        // A FrameRequest header announcing a 1 GiB crop.
        let mut bytes = vec![0x03];
        bytes.extend_from_slice(&[0; 18]);
        bytes.extend_from_slice(&[0, 112, 0, 112, 0]);
        bytes.extend_from_slice(&(1_u32 << 30).to_le_bytes());
        let _ = bad.send_stream_bytes(&bytes).await;
        bad.close_code().await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn garbage_datagram_is_closed_malformed() {
    misbehaviour_next_to_good_client("garbage datagram", CloseCode::Malformed, |bad| async move {
        let _ = bad.send_datagram(Bytes::from_static(&[0xff, 0x00, 0x13, 0x37]));
        bad.close_code().await
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn duplicate_frame_id_is_a_protocol_violation() {
    misbehaviour_next_to_good_client(
        "duplicate frame id",
        CloseCode::ProtocolViolation,
        |bad| async move {
            let f = frame(5, 0, DEADLINE_MS);
            let _ = bad.send_frame(&f).await;
            let _ = bad.send_frame(&f).await;
            bad.close_code().await
        },
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn second_hello_is_a_protocol_violation() {
    misbehaviour_next_to_good_client(
        "second hello",
        CloseCode::ProtocolViolation,
        |mut bad| async move {
            let mut buf = bytes::BytesMut::new();
            holoface_protocol::encode_framed(&Message::ClientHello(hello(TEST_TOKEN)), &mut buf).unwrap();
            let _ = bad.send_control_bytes(&buf).await;
            bad.close_code().await
        },
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn flooding_client_is_shed_then_closed_overloaded() {
    let reference = reference(9);
    let mut s = settings();
    s.max_frame_rate = 50;
    let server = RunningServer::start(s).await.unwrap();
    let mut good = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    let mut flooder = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    // The flooder opens frame streams as fast as flow control lets it,
    // while another task reads its replies.
    let conn = flooder.conn.clone();
    let sender = tokio::spawn(async move {
        let mut sent = 0_u64;
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        while tokio::time::Instant::now() < deadline {
            if send_frame_on(&conn, &frame(sent + 1, 1, DEADLINE_MS))
                .await
                .is_err()
            {
                break;
            }
            sent += 1;
        }
        sent
    });
    let reader = tokio::spawn(async move {
        let mut replies = 0_usize;
        while let Ok(Ok(_)) = tokio::time::timeout(Duration::from_secs(5), flooder.next_reply()).await {
            replies += 1;
        }
        (replies, flooder)
    });
    let mut good_latencies = Vec::new();
    for id in 1..=5 {
        let t = std::time::Instant::now();
        let reply = within("good reply under flood", good.request(&frame(id, 9, DEADLINE_MS)))
            .await
            .unwrap();
        good_latencies.push(t.elapsed());
        assert_landmarks(&reply, &reference);
    }
    let sent = within("flood sender", sender).await.unwrap();
    let (_replies, flooder) = within("flood reader", reader).await.unwrap();
    assert!(sent > 50, "the flooder sent {sent} frames");
    assert_eq!(
        within("flooder closed", flooder.close_code()).await,
        Some(CloseCode::Overloaded)
    );
    assert!(
        server.metrics.drops_for(DropReason::Superseded) > 0,
        "flooded frames were superseded, not queued"
    );
    assert_eq!(server.metrics.closes_for(CloseCode::Overloaded), 1);
    // The good client is still served after the flooder is gone.
    let reply = within("good reply after flood", good.request(&frame(99, 9, DEADLINE_MS)))
        .await
        .unwrap();
    assert_landmarks(&reply, &reference);
    eprintln!("good client latencies under flood: {good_latencies:?}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_cap_closes_extra_clients_overloaded() {
    let mut s = settings();
    s.max_clients = 1;
    let server = RunningServer::start(s).await.unwrap();
    let mut first = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    let code = within(
        "over cap",
        refused_with(server.addr, server.fingerprint, hello(TEST_TOKEN)),
    )
    .await;
    assert_eq!(code, Some(CloseCode::Overloaded));
    assert!(
        within("first still served", first.request(&frame(1, 2, DEADLINE_MS)))
            .await
            .is_ok()
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_sends_goaway_and_closes_shutting_down() {
    let server = RunningServer::start(settings()).await.unwrap();
    let mut client = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    assert!(
        within("reply", client.request(&frame(1, 4, DEADLINE_MS)))
            .await
            .is_ok()
    );
    // One frame in flight when shutdown starts: it is answered, not lost.
    client.send_frame(&frame(2, 4, DEADLINE_MS)).await.unwrap();
    let stop = tokio::spawn(server.shutdown());
    let goaway = within("goaway", client.next_control()).await.unwrap();
    assert!(
        matches!(&goaway, Message::Goaway(g) if g.reason == CloseCode::ShuttingDown),
        "{goaway:?}"
    );
    let last = within("in-flight reply", client.next_reply()).await.unwrap();
    assert_eq!(last.frame_id, 2);
    assert!(
        matches!(
            last.outcome,
            ReplyOutcome::Landmarks { .. }
                | ReplyOutcome::Dropped {
                    reason: DropReason::ShuttingDown
                }
        ),
        "{last:?}"
    );
    assert_eq!(
        within("close", client.close_code()).await,
        Some(CloseCode::ShuttingDown)
    );
    within("server stopped", stop).await.unwrap().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_and_health_are_served_on_loopback() {
    let mut s = settings();
    s.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    let server = RunningServer::start(s).await.unwrap();
    let addr = server.metrics_addr.expect("metrics listener");
    assert_eq!(
        refused_with(server.addr, server.fingerprint, hello("nope")).await,
        Some(CloseCode::Unauthorized)
    );
    let mut client = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    client.request(&frame(1, 1, DEADLINE_MS)).await.unwrap();
    let get = |path: &'static str| async move {
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        s.write_all(format!("GET {path} HTTP/1.1\r\n\r\n").as_bytes())
            .await
            .unwrap();
        let mut out = String::new();
        s.read_to_string(&mut out).await.unwrap();
        out
    };
    assert!(get("/health").await.starts_with("HTTP/1.1 200"));
    let m = get("/metrics").await;
    for needle in [
        "holoface_connected_clients 1",
        "holoface_auth_failures_total{reason=\"unauthorized\"} 1",
        "holoface_frames_aligned_total 1",
        "holoface_batch_size_count 1",
        "holoface_inference_seconds_count 1",
        "holoface_client_lost_packets_total ",
    ] {
        assert!(m.contains(needle), "missing {needle} in\n{m}");
    }
    assert!(
        m.contains("holoface_client_rtt_seconds_count")
            && !m.contains("holoface_client_rtt_seconds_count 0\n"),
        "client RTT sampled:\n{m}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test]
async fn missing_model_is_a_clear_startup_error() {
    let mut s = settings();
    s.engine.model = "/nonexistent/dan.onnx".into();
    let err = RunningServer::start(s).await.unwrap_err().to_string();
    assert!(
        err.contains("DAN model not found at /nonexistent/dan.onnx")
            && err.contains("engine.model")
            && err.contains("holoface setup"),
        "{err}"
    );
    let mut s = settings();
    s.engine.ort_dylib = "/nonexistent/libonnxruntime.so".into();
    s.engine.model = model_path();
    let err = RunningServer::start(s).await.unwrap_err().to_string();
    assert!(
        err.contains("ONNX Runtime library not found at /nonexistent/libonnxruntime.so"),
        "{err}"
    );
}

#[tokio::test]
async fn non_onnx_model_file_is_rejected() {
    let path = std::env::temp_dir().join(format!("holoface-not-a-model-{}.onnx", std::process::id()));
    std::fs::write(&path, b"definitely not protobuf").unwrap();
    let mut s = settings();
    s.engine.model = path.clone();
    let err = RunningServer::start(s).await.unwrap_err().to_string();
    let _ = std::fs::remove_file(&path);
    assert!(err.contains("ONNX Runtime"), "{err}");
}

/// The first datagram a QUIC client sends (its Initial), captured on a socket that never answers.
async fn captured_initial(fingerprint: holoface_quic::Fingerprint) -> Vec<u8> {
    let sink = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let endpoint = client_endpoint(fingerprint).unwrap();
    let _connecting = endpoint.connect(sink.local_addr().unwrap(), "localhost").unwrap();
    let mut buf = vec![0u8; 2048];
    let (n, _) = within("the client's Initial", sink.recv_from(&mut buf))
        .await
        .unwrap();
    buf.truncate(n);
    buf
}

/// Issue 16, defect 1: unauthenticated connections cannot lock valid clients out. 300 connections finish the
/// TLS handshake and never send a hello (re-opened all along while the valid client connects), and 70
/// handshakes never get past their Initial packet; a valid client still connects and its frames are answered
/// within their deadline, and the idle ones never took a client slot.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_and_half_open_connections_do_not_lock_out_a_valid_client() {
    let mut s = settings();
    s.max_clients = 10;
    let server = RunningServer::start(s).await.unwrap();
    let (addr, fp) = (server.addr, server.fingerprint);

    // 70 half-open handshakes: the same Initial replayed from 70 sockets that never answer.
    let initial = captured_initial(fp).await;
    let mut half_open = Vec::new();
    for _ in 0..70 {
        let sock = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        sock.send_to(&initial, addr).await.unwrap();
        half_open.push(sock);
    }
    // 300 idle connections (TLS done, no hello), then more of them, continuously, in the background.
    let (count, mut opened_so_far) = tokio::sync::watch::channel(0_usize);
    let attack = tokio::spawn(async move {
        let endpoint = client_endpoint(fp).unwrap();
        let mut held = std::collections::VecDeque::new();
        let mut opened = 0_usize;
        loop {
            if let Ok(Ok(c)) =
                tokio::time::timeout(Duration::from_secs(2), connect_raw(&endpoint, addr)).await
            {
                held.push_back(c);
                opened += 1;
                count.send_replace(opened);
            }
            if held.len() > 300 {
                held.pop_front();
            }
            if opened >= 600 {
                return opened;
            }
        }
    });
    // The valid client comes once the first 300 have piled up.
    within("300 idle connections", opened_so_far.wait_for(|&n| n >= 300))
        .await
        .unwrap();

    let mut good = within(
        "a valid client's handshake",
        TestClient::connect(addr, fp, hello(TEST_TOKEN)),
    )
    .await
    .expect("a valid client connects despite the idle and half-open connections");
    for id in 1..=5 {
        let sent = std::time::Instant::now();
        let reply = within("a reply", good.request(&frame(id, 3, DEADLINE_MS)))
            .await
            .unwrap();
        assert!(
            matches!(reply.outcome, ReplyOutcome::Landmarks { .. }),
            "{reply:?}"
        );
        assert!(sent.elapsed() < Duration::from_millis(u64::from(DEADLINE_MS)));
    }
    let m = &server.metrics;
    assert_eq!(
        m.connected_clients.load(std::sync::atomic::Ordering::Relaxed),
        1,
        "only the authenticated client holds a client slot"
    );
    let evicted = m.pending_evicted.load(std::sync::atomic::Ordering::Relaxed);
    let retries = m.pending_retries.load(std::sync::atomic::Ordering::Relaxed);
    eprintln!("pending evicted {evicted}, retries {retries}");
    assert!(evicted + retries > 0, "the pending budget was under pressure");
    attack.abort();
    drop(half_open);
    server.shutdown().await.unwrap();
}

/// A connection that finishes TLS and never sends its hello is closed `ProtocolViolation` at the hello
/// timeout (and never held a client slot meanwhile).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_hello_within_the_hello_timeout_is_a_protocol_violation() {
    let mut s = settings();
    s.hello_timeout = Duration::from_millis(300);
    let server = RunningServer::start(s).await.unwrap();
    let endpoint =
        holoface_tests::client_endpoint_with(server.fingerprint, Some(Duration::from_millis(100))).unwrap();
    let conn = connect_raw(&endpoint, server.addr).await.unwrap();
    let started = std::time::Instant::now();
    let code = holoface_tests::app_close_code(&within("the hello timeout", conn.closed()).await);
    assert_eq!(code, Some(CloseCode::ProtocolViolation));
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "closed at the 300 ms hello timeout"
    );
    assert_eq!(
        server
            .metrics
            .connected_clients
            .load(std::sync::atomic::Ordering::Relaxed),
        0
    );
    server.shutdown().await.unwrap();
}

/// Issue 16, defect 5: a client that ignores the Goaway and keeps opening frame streams cannot stretch the
/// shutdown: its new streams are refused, it is closed with `ShuttingDown` (not 0), and `run` returns within
/// the configured bound.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_is_bounded_and_closes_shutting_down_when_a_client_ignores_goaway() {
    let mut s = settings();
    s.shutdown_timeout = Duration::from_secs(2);
    let server = RunningServer::start(s).await.unwrap();
    let mut client = TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN))
        .await
        .unwrap();
    assert!(
        within("first reply", client.request(&frame(1, 5, DEADLINE_MS)))
            .await
            .is_ok()
    );
    let conn = client.conn.clone();
    let (count, mut sent_so_far) = tokio::sync::watch::channel(0_u64);
    let stubborn = tokio::spawn(async move {
        let mut id = 2;
        while conn.close_reason().is_none() {
            let _ = send_frame_on(&conn, &frame(id, 5, DEADLINE_MS)).await;
            count.send_replace(id - 1);
            id += 1;
            // A client's pace, not a wait for something.
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        id
    });
    // The shutdown starts while the stubborn client is sending.
    within(
        "the stubborn sender's first frames",
        sent_so_far.wait_for(|&n| n >= 10),
    )
    .await
    .unwrap();
    let started = std::time::Instant::now();
    server.shutdown().await.unwrap();
    let took = started.elapsed();
    let code = within("the close", client.close_code()).await;
    assert_eq!(code, Some(CloseCode::ShuttingDown));
    assert!(
        took <= Duration::from_millis(2_500),
        "shutdown took {took:?} with a 2 s bound"
    );
    let sent = within("the stubborn sender stops", stubborn).await.unwrap();
    eprintln!(
        "shutdown took {took:?}; the client had opened {} frame streams",
        sent - 2
    );
}

#[test]
fn cuda_on_the_cpu_library_falls_back_naming_the_gpu_build() {
    let mut opts = loopback_settings().engine;
    opts.provider = holoface_inference::Provider::Cuda {
        device: 0,
        required: false,
    };
    let engine = OnnxEngine::load(&opts).unwrap();
    let execution = engine.execution();
    assert_eq!(execution.provider, holoface_inference::CPU_PROVIDER);
    let why = execution.fallback.unwrap_or_default();
    assert!(
        why.contains("without the CUDA execution provider") && why.contains("make ort-gpu"),
        "{why}"
    );
}

/// The half-precision DAN (`make dan-fp16`): `$HOLOFACE_DAN_FP16_MODEL`, else `.cache/models/`.
fn fp16_model() -> std::path::PathBuf {
    let path = std::env::var_os("HOLOFACE_DAN_FP16_MODEL")
        .filter(|v| !v.is_empty())
        .map_or_else(
            || holoface_tests::workspace_root().join(".cache/models/dan.fp16.onnx"),
            std::path::PathBuf::from,
        );
    assert!(
        path.is_file(),
        "fp16 DAN not found at {} (run `make dan-fp16`)",
        path.display()
    );
    path
}

/// `other` (a conversion of the shipped fp32 model to `precision`) loads under the same contract, declares its
/// precision and answers four crops within `max_shift` px and `max_prob` of the fp32 model.
fn agrees_with_fp32(other: std::path::PathBuf, precision: &str, max_shift: f32, max_prob: f32) {
    let mut opts = loopback_settings().engine;
    opts.max_batch = 4;
    let mut fp32 = OnnxEngine::load(&opts).unwrap();
    opts.model = other;
    let mut conv = match OnnxEngine::load(&opts) {
        Ok(conv) => conv,
        // On a CPU without VNNI ONNX Runtime's int8 kernels saturate; the self-test may refuse the model there,
        // and must then say why (the server's `auto` never picks int8 on such a CPU).
        Err(holoface_inference::EngineError::SelfTest { detail, .. })
            if precision == "int8" && !holoface_inference::CpuInt8::detect().has_vnni() =>
        {
            assert!(
                detail.contains("has no VNNI") && detail.contains("serve fp32"),
                "{detail}"
            );
            eprintln!("int8 refused on this CPU without VNNI: {detail}");
            return;
        }
        Err(e) => panic!("{e}"),
    };
    assert_eq!(
        (fp32.info().precision.as_str(), conv.info().precision.as_str()),
        ("fp32", precision)
    );
    assert_eq!(
        conv.info().mean_shape,
        fp32.info().mean_shape,
        "same model, same contract"
    );
    let mut batch = BatchTensor::new(4, 112 * 112);
    for seed in [0, 60, 120, 180] {
        batch.push(&frame(0, seed, 0).crop.data).unwrap();
    }
    let mut a = vec![LandmarkOut::default(); 4];
    let mut b = vec![LandmarkOut::default(); 4];
    fp32.infer(&batch, &mut a).unwrap();
    conv.infer(&batch, &mut b).unwrap();
    for (x, y) in a.iter().zip(&b) {
        assert!(y.problem(68).is_none());
        let shift = x
            .landmarks
            .iter()
            .zip(&y.landmarks)
            .map(|(p, q)| (p[0] - q[0]).hypot(p[1] - q[1]))
            .fold(0.0_f32, f32::max);
        assert!(shift < max_shift, "{precision} moved a landmark by {shift} px");
        assert!(
            (x.face_prob - y.face_prob).abs() < max_prob,
            "{} vs {}",
            x.face_prob,
            y.face_prob
        );
    }
}

#[test]
fn the_fp16_model_loads_under_the_same_contract_and_agrees_with_fp32() {
    agrees_with_fp32(fp16_model(), "fp16", 0.5, 1e-2);
}

/// The int8 DAN (`make dan-int8`, committed): `$HOLOFACE_DAN_INT8_MODEL`, else `models/assets/dan.int8.onnx`.
fn int8_model() -> std::path::PathBuf {
    let path = std::env::var_os("HOLOFACE_DAN_INT8_MODEL")
        .filter(|v| !v.is_empty())
        .map_or_else(
            || holoface_tests::workspace_root().join("models/assets/dan.int8.onnx"),
            std::path::PathBuf::from,
        );
    assert!(
        path.is_file(),
        "int8 DAN not found at {} (run `make dan-int8`)",
        path.display()
    );
    path
}

#[test]
fn the_int8_model_loads_under_the_same_contract_and_agrees_with_fp32() {
    // On the validation faces the int8 graph moves a landmark by 0.05 px on average, 0.32 px at most
    // (models/dan/to_int8.py); these synthetic frames are no faces, so allow a little more.
    agrees_with_fp32(int8_model(), "int8", 1.5, 0.05);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_serves_the_precision_it_is_told_or_the_rule_picks_and_says_which() {
    use holoface_inference::{CpuInt8, PrecisionChoice};
    let cpu = CpuInt8::detect();
    for (choice, want) in [
        (PrecisionChoice::Int8, "int8"),
        (PrecisionChoice::Fp32, "fp32"),
        (
            PrecisionChoice::Auto,
            if cpu.has_vnni() { "int8" } else { "fp32" },
        ),
    ] {
        let mut s = loopback_settings();
        s.precision = choice;
        s.int8_model = int8_model();
        let server = match RunningServer::start(s).await {
            Ok(server) => server,
            // int8 asked for on a CPU without VNNI: refused by the self-test, which says why (see above).
            Err(e) if want == "int8" && !cpu.has_vnni() => {
                let e = format!("{e:#}");
                assert!(e.contains("has no VNNI"), "{e}");
                continue;
            }
            Err(e) => panic!("{choice:?}: {e:#}"),
        };
        let client = tokio::time::timeout(
            WAIT,
            TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN)),
        )
        .await
        .unwrap()
        .unwrap();
        assert_eq!(
            client.welcome.model_version,
            format!("0.4.0+{want}"),
            "{choice:?}: the model string is all a client sees of the choice"
        );
        let text = server.metrics.render();
        assert!(
            text.contains(&format!("precision=\"{want}\",cpu_int8=\"{}\"", cpu.label())),
            "{choice:?}: {text}"
        );
        drop(client);
        server.shutdown().await.unwrap();
    }
    // Auto with no int8 file: fp32 serves (the log says where it looked).
    let mut s = loopback_settings();
    s.precision = PrecisionChoice::Auto;
    s.int8_model = std::path::PathBuf::from("/nonexistent/dan.int8.onnx");
    let server = RunningServer::start(s).await.unwrap();
    assert!(server.metrics.render().contains("precision=\"fp32\""));
    server.shutdown().await.unwrap();
    // A file of another precision than asked for stops the start, naming the setting.
    let mut s = loopback_settings();
    s.precision = PrecisionChoice::Fp16;
    let e = RunningServer::start(s).await.unwrap_err().to_string();
    assert!(
        e.contains("fp32 graph") && e.contains("engine.precision = \"fp16\""),
        "{e}"
    );
    // Auto on a VNNI CPU with engine.int8_model pointing at an fp32 file: a wrong file, refused by name.
    if cpu.has_vnni() {
        let mut s = loopback_settings();
        s.precision = PrecisionChoice::Auto;
        s.int8_model = model_path();
        let e = RunningServer::start(s).await.unwrap_err().to_string();
        assert!(e.contains("an fp32 graph") && e.contains("int8_model"), "{e}");
    }
}
