//! Property tests for the wire codec and the recording format: round trips,
//! every truncation, every single-bit flip.
// Helpers and strategies outside #[test] fns unwrap too; a panic is a test failure.
#![allow(clippy::unwrap_used)]

use bytes::{BufMut, Bytes, BytesMut};
use holoface_protocol::limits::{
    MAX_CROP_DIM, MAX_ENCODINGS, MAX_ERROR_TEXT_LEN, MAX_LANDMARKS, MAX_MESSAGE_LEN, MAX_NAME_LEN,
    MAX_SOURCE_LEN, MAX_TOKEN_LEN,
};
use holoface_protocol::{
    CameraIntrinsics, ClientHello, CloseCode, Crop, CropEncoding, Decode, DecodeError, DropReason, ErrorMsg,
    FramePayload, FrameRecord, FrameReply, FrameRequest, Goaway, Message, RecordingError, RecordingHeader,
    RecordingReader, RecordingWriter, ReplyChannel, ReplyOutcome, ServerWelcome, decode_framed,
    encode_framed,
};
use proptest::prelude::*;

// ---------------------------------------------------------------- strategies

fn finite() -> impl Strategy<Value = f32> {
    use proptest::num::f32::{NEGATIVE, NORMAL, POSITIVE, SUBNORMAL, ZERO};
    POSITIVE | NEGATIVE | NORMAL | SUBNORMAL | ZERO
}

fn point() -> impl Strategy<Value = [f32; 2]> {
    [finite(), finite()]
}

fn points(max: usize) -> impl Strategy<Value = Vec<[f32; 2]>> {
    prop_oneof![
        4 => prop::collection::vec(point(), 0..=8),
        1 => prop::collection::vec(point(), max..=max),
    ]
}

/// Strings up to `max` bytes, sometimes exactly at the limit, with multi-byte chars.
fn text(max: usize) -> impl Strategy<Value = String> {
    prop_oneof![
        4 => "[a-z0-9 é€😀-]{0,12}".prop_filter("fits", move |s| s.len() <= max),
        1 => Just("x".repeat(max)),
    ]
}

fn encoding() -> impl Strategy<Value = CropEncoding> {
    prop::sample::select(CropEncoding::ALL)
}

fn close_code() -> impl Strategy<Value = CloseCode> {
    prop::sample::select(&CloseCode::ALL[..])
}

fn crop() -> impl Strategy<Value = Crop> {
    let raw = (1_u16..=12, 1_u16..=12).prop_flat_map(|(w, h)| {
        prop::collection::vec(any::<u8>(), usize::from(w) * usize::from(h))
            .prop_map(move |data| Crop::raw(w, h, data))
    });
    let compressed = (
        prop_oneof![Just(CropEncoding::Png), Just(CropEncoding::Jpeg)],
        1..=MAX_CROP_DIM,
        1..=MAX_CROP_DIM,
        prop::collection::vec(any::<u8>(), 0..48),
    )
        .prop_map(|(encoding, width, height, data)| Crop {
            encoding,
            width,
            height,
            data: data.into(),
        });
    prop_oneof![raw, compressed]
}

fn client_hello() -> impl Strategy<Value = ClientHello> {
    (
        any::<u16>(),
        text(MAX_TOKEN_LEN),
        text(MAX_NAME_LEN),
        prop::collection::vec(encoding(), 0..=MAX_ENCODINGS),
        any::<u16>(),
    )
        .prop_map(
            |(version, token, client_name, encodings, max_in_flight)| ClientHello {
                version,
                token,
                client_name,
                encodings,
                max_in_flight,
            },
        )
}

fn server_welcome() -> impl Strategy<Value = ServerWelcome> {
    (
        (any::<u16>(), text(MAX_NAME_LEN), text(MAX_NAME_LEN), any::<u16>()),
        points(MAX_LANDMARKS),
        finite(),
        encoding(),
        prop::sample::select(ReplyChannel::ALL),
        any::<u16>(),
        any::<u32>(),
    )
        .prop_map(
            |(
                (version, model_id, model_version, crop_size),
                mean_shape,
                face_threshold,
                encoding,
                reply_channel,
                max_in_flight,
                max_frame_age_ms,
            )| ServerWelcome {
                version,
                model_id,
                model_version,
                landmark_count: u16::try_from(mean_shape.len()).unwrap(),
                crop_size,
                mean_shape,
                face_threshold,
                encoding,
                reply_channel,
                max_in_flight,
                max_frame_age_ms,
            },
        )
}

fn frame_request() -> impl Strategy<Value = FrameRequest> {
    (any::<u64>(), any::<u64>(), any::<u16>(), crop(), any::<u16>()).prop_map(
        |(frame_id, captured_at_us, deadline_ms, crop, track_id)| FrameRequest {
            frame_id,
            captured_at_us,
            deadline_ms,
            crop,
            track_id,
        },
    )
}

fn frame_reply() -> impl Strategy<Value = FrameReply> {
    let landmarks = (points(MAX_LANDMARKS), finite(), any::<u32>(), any::<u32>()).prop_map(
        |(landmarks, face_prob, queue_us, infer_us)| ReplyOutcome::Landmarks {
            landmarks,
            face_prob,
            queue_us,
            infer_us,
        },
    );
    let dropped = prop::sample::select(DropReason::ALL).prop_map(|reason| ReplyOutcome::Dropped { reason });
    (any::<u64>(), prop_oneof![landmarks, dropped], any::<u16>()).prop_map(|(frame_id, outcome, track_id)| {
        FrameReply {
            frame_id,
            outcome,
            track_id,
        }
    })
}

fn message() -> impl Strategy<Value = Message> {
    prop_oneof![
        client_hello().prop_map(Message::from),
        server_welcome().prop_map(Message::from),
        frame_request().prop_map(Message::from),
        frame_reply().prop_map(Message::from),
        (close_code(), text(MAX_ERROR_TEXT_LEN)).prop_map(|(reason, text)| Goaway { reason, text }.into()),
        (close_code(), text(MAX_ERROR_TEXT_LEN)).prop_map(|(code, text)| ErrorMsg { code, text }.into()),
    ]
}

fn recording_header() -> impl Strategy<Value = RecordingHeader> {
    (
        [finite(), finite(), finite(), finite()],
        any::<u32>(),
        any::<u32>(),
        text(MAX_SOURCE_LEN),
        any::<u64>(),
    )
        .prop_map(
            |([fx, fy, cx, cy], width, height, source, created_unix_ms)| RecordingHeader {
                intrinsics: CameraIntrinsics {
                    fx,
                    fy,
                    cx,
                    cy,
                    width,
                    height,
                },
                source,
                created_unix_ms,
            },
        )
}

fn frame_record() -> impl Strategy<Value = FrameRecord> {
    let crop_payload =
        ([finite(), finite(), finite(), finite()], crop()).prop_map(|(image_from_crop, crop)| {
            FramePayload::Crop {
                image_from_crop,
                crop,
            }
        });
    let full_raw = (1_u32..=16, 1_u32..=16).prop_flat_map(|(width, height)| {
        prop::collection::vec(any::<u8>(), (width * height) as usize).prop_map(move |data| {
            FramePayload::FullFrame {
                width,
                height,
                encoding: CropEncoding::Raw,
                data: data.into(),
            }
        })
    });
    let full_png = (
        1_u32..=8192,
        1_u32..=8192,
        prop::collection::vec(any::<u8>(), 0..32),
    )
        .prop_map(|(width, height, data)| FramePayload::FullFrame {
            width,
            height,
            encoding: CropEncoding::Png,
            data: data.into(),
        });
    (
        any::<u64>(),
        prop::array::uniform16(finite()),
        prop_oneof![crop_payload, full_raw, full_png],
        prop::option::of(prop::collection::vec(point(), 0..=MAX_LANDMARKS)),
        prop::option::of(any::<bool>()),
    )
        .prop_map(
            |(timestamp_us, camera_to_world, payload, ground_truth, face_present)| FrameRecord {
                timestamp_us,
                camera_to_world,
                payload,
                ground_truth,
                face_present,
            },
        )
}

// ---------------------------------------------------------------- helpers

fn encode(msg: &Message) -> Bytes {
    let mut buf = BytesMut::new();
    msg.encode(&mut buf).unwrap();
    buf.freeze()
}

fn encode_file(header: &RecordingHeader, records: &[FrameRecord]) -> Vec<u8> {
    let mut w = RecordingWriter::new(Vec::new(), header).unwrap();
    for r in records {
        w.write_record(r).unwrap();
    }
    w.finish().unwrap()
}

fn read_all(bytes: &[u8]) -> Result<Vec<FrameRecord>, RecordingError> {
    RecordingReader::new(bytes)?.collect()
}

/// Start offset of each record, plus the end of the file.
fn record_offsets(header_len: usize, records: &[FrameRecord]) -> Vec<usize> {
    let mut offsets = vec![header_len];
    for r in records {
        offsets.push(offsets.last().unwrap() + 8 + r.encoded_body_len());
    }
    offsets
}

/// `n` cases natively; an eighth of them under emulation (`make arm64-test` runs the aarch64 build under
/// qemu, where a bit-flip property takes about 0.15 s a case): there they check the ARM build of the same codec,
/// and the native run covers the input space.
fn cases(n: u32) -> ProptestConfig {
    let emulated = std::env::var_os("HOLOFACE_EMULATED").is_some();
    ProptestConfig::with_cases(if emulated { n / 8 } else { n })
}

// ---------------------------------------------------------------- messages

proptest! {
    #![proptest_config(cases(256))]

    #[test]
    fn message_round_trips(msg in message()) {
        let wire = encode(&msg);
        prop_assert_eq!(wire.len(), msg.encoded_len());
        prop_assert_eq!(Message::decode(wire.clone()).unwrap(), msg.clone());

        // The body types round-trip through Encode/Decode on their own too (a tracked frame's body follows
        // its track id; the body itself carries no track).
        let tracked = matches!(wire[0], Message::TAG_TRACKED_FRAME_REQUEST | Message::TAG_TRACKED_FRAME_REPLY);
        let track_id = if tracked { u16::from_le_bytes([wire[1], wire[2]]) } else { 0 };
        let mut body = wire.slice(if tracked { 3 } else { 1 }..);
        let again: Message = match &msg {
            Message::ClientHello(_) => ClientHello::decode(&mut body).unwrap().into(),
            Message::ServerWelcome(_) => ServerWelcome::decode(&mut body).unwrap().into(),
            Message::FrameRequest(_) => FrameRequest { track_id, ..FrameRequest::decode(&mut body).unwrap() }.into(),
            Message::FrameReply(_) => FrameReply { track_id, ..FrameReply::decode(&mut body).unwrap() }.into(),
            Message::Goaway(_) => Goaway::decode(&mut body).unwrap().into(),
            Message::Error(_) => ErrorMsg::decode(&mut body).unwrap().into(),
        };
        prop_assert!(body.is_empty());
        prop_assert_eq!(again, msg);
    }

    #[test]
    fn every_strict_prefix_is_an_error(msg in message()) {
        let wire = encode(&msg);
        for i in 0..wire.len() {
            prop_assert!(Message::decode(wire.slice(..i)).is_err(), "prefix {} of {} decoded", i, wire.len());
        }
        // Trailing garbage is refused.
        let mut longer = BytesMut::from(&wire[..]);
        longer.put_u8(0);
        prop_assert_eq!(Message::decode(longer.freeze()), Err(DecodeError::TrailingBytes { len: 1 }));
    }

    #[test]
    fn framed_prefixes_need_more_bytes(msg in message()) {
        let mut framed = BytesMut::new();
        encode_framed(&msg, &mut framed).unwrap();
        for i in 0..framed.len() {
            let mut partial = BytesMut::from(&framed[..i]);
            prop_assert_eq!(decode_framed(&mut partial), Ok(None));
            prop_assert_eq!(partial.len(), i, "nothing consumed");
        }
        let mut full = framed.clone();
        prop_assert_eq!(decode_framed(&mut full), Ok(Some(msg)));
        prop_assert!(full.is_empty());
    }

    #[test]
    fn framed_stream_survives_any_chunking(
        msgs in prop::collection::vec(message(), 1..6),
        chunks in prop::collection::vec(1_usize..64, 1..32),
    ) {
        let mut wire = BytesMut::new();
        for m in &msgs {
            encode_framed(m, &mut wire).unwrap();
        }
        let mut rx = BytesMut::new();
        let mut out = Vec::new();
        let mut pos = 0;
        let mut chunk = chunks.iter().cycle();
        while pos < wire.len() {
            let end = (pos + chunk.next().unwrap()).min(wire.len());
            rx.extend_from_slice(&wire[pos..end]);
            pos = end;
            while let Some(m) = decode_framed(&mut rx).unwrap() {
                out.push(m);
            }
        }
        prop_assert_eq!(out, msgs);
        prop_assert!(rx.is_empty());
    }

    #[test]
    fn arbitrary_bytes_never_panic(data in prop::collection::vec(any::<u8>(), 0..256)) {
        let _ = Message::decode(Bytes::from(data.clone()));
        let mut buf = BytesMut::from(&data[..]);
        while let Ok(Some(_)) = decode_framed(&mut buf) {}
    }
}

proptest! {
    #![proptest_config(cases(64))]

    #[test]
    fn every_bit_flip_is_ok_or_typed_error(msg in message()) {
        let wire = encode(&msg).to_vec();
        let mut framed = BytesMut::new();
        encode_framed(&msg, &mut framed).unwrap();
        let framed = framed.to_vec();
        for bit in 0..wire.len() * 8 {
            let mut v = wire.clone();
            v[bit / 8] ^= 1 << (bit % 8);
            // Any Ok or Err is fine; a panic fails the test.
            let _ = Message::decode(Bytes::from(v));
        }
        for bit in 0..framed.len() * 8 {
            let mut v = BytesMut::from(&framed[..]);
            v[bit / 8] ^= 1 << (bit % 8);
            match decode_framed(&mut v) {
                Ok(_) => {}
                Err(e) => prop_assert!(!e.is_short(), "framed decoder returned Short: {e:?}"),
            }
        }
    }
}

#[test]
fn oversize_length_prefixes_are_rejected_up_front() {
    // Framed: 4 GiB - 1 announced, 3 bytes present.
    let mut rx = BytesMut::from(&[0xff, 0xff, 0xff, 0xff, 1, 2, 3][..]);
    assert_eq!(
        decode_framed(&mut rx),
        Err(DecodeError::TooLarge {
            field: "message",
            len: u32::MAX as usize,
            max: MAX_MESSAGE_LEN
        })
    );
    assert_eq!(rx.len(), 7, "nothing consumed");

    // Whole message: token of 65535 bytes announced, 2 present.
    let v = vec![0x01, 1, 0, 0xff, 0xff, b'a', b'b'];
    assert_eq!(
        Message::decode(Bytes::from(v)),
        Err(DecodeError::TooLarge {
            field: "token",
            len: 65535,
            max: MAX_TOKEN_LEN
        })
    );

    // Crop payload of 4 GiB announced.
    let mut v = vec![0x03];
    v.extend_from_slice(&[0; 18]);
    v.extend_from_slice(&[1, 8, 0, 8, 0, 0xff, 0xff, 0xff, 0xff, 0]);
    assert!(matches!(
        Message::decode(Bytes::from(v)),
        Err(DecodeError::TooLarge {
            field: "crop.data",
            len: 0xffff_ffff,
            ..
        })
    ));

    // 65535 landmarks announced.
    let v = vec![0x04, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0xff, 0xff, 0, 0];
    assert!(matches!(
        Message::decode(Bytes::from(v)),
        Err(DecodeError::TooLarge {
            field: "landmarks",
            len: 65535,
            ..
        })
    ));
}

// ---------------------------------------------------------------- recordings

proptest! {
    #![proptest_config(cases(64))]

    #[test]
    fn recording_round_trips(header in recording_header(), records in prop::collection::vec(frame_record(), 0..4)) {
        let file = encode_file(&header, &records);
        let header_bytes = header.encode().unwrap();
        prop_assert_eq!(&file[..header_bytes.len()], &header_bytes[..]);
        prop_assert_eq!(RecordingHeader::decode(&file).unwrap(), header.clone());

        let mut reader = RecordingReader::new(&file[..]).unwrap();
        prop_assert_eq!(reader.header(), &header);
        let got: Vec<FrameRecord> = reader.by_ref().collect::<Result<_, _>>().unwrap();
        prop_assert_eq!(&got, &records);
        prop_assert_eq!(reader.offset(), file.len() as u64);

        for r in &records {
            let mut body = BytesMut::new();
            r.encode_body(&mut body).unwrap();
            prop_assert_eq!(body.len(), r.encoded_body_len());
            prop_assert_eq!(&FrameRecord::decode_body(body.freeze()).unwrap(), r);
        }
    }

    #[test]
    fn every_truncation_is_detected(header in recording_header(), records in prop::collection::vec(frame_record(), 1..4)) {
        let file = encode_file(&header, &records);
        let header_len = header.encode().unwrap().len();
        let offsets = record_offsets(header_len, &records);
        prop_assert_eq!(*offsets.last().unwrap(), file.len());
        for cut in 0..file.len() {
            let res = read_all(&file[..cut]);
            if cut < header_len {
                let is_header_truncated = matches!(res, Err(RecordingError::HeaderTruncated { .. }));
                prop_assert!(is_header_truncated, "cut {}: {:?}", cut, res);
            } else if let Some(k) = offsets.iter().position(|&o| o == cut) {
                // Exactly at a record boundary: a shorter, valid file.
                prop_assert_eq!(res.unwrap(), records[..k].to_vec());
            } else {
                let k = offsets.iter().rposition(|&o| o < cut).unwrap();
                match res {
                    Err(RecordingError::Truncated { record_index, offset }) => {
                        prop_assert_eq!(record_index, k as u64);
                        prop_assert_eq!(offset, offsets[k] as u64);
                    }
                    other => prop_assert!(false, "cut {}: {:?}", cut, other),
                }
            }
        }
    }

    #[test]
    fn a_file_cut_anywhere_is_read_up_to_its_last_whole_record_when_cuts_are_tolerated(header in recording_header(), records in prop::collection::vec(frame_record(), 1..4)) {
        // What a writer killed part-way leaves: every whole record is read, then the reading ends and says where
        // the file was cut; never an error, never more than the file holds.
        let file = encode_file(&header, &records);
        let header_len = header.encode().unwrap().len();
        let offsets = record_offsets(header_len, &records);
        for cut in header_len..=file.len() {
            let mut reader = RecordingReader::new(&file[..cut]).unwrap().tolerate_cut();
            let mut got = Vec::new();
            while let Some(r) = reader.next_record().unwrap() {
                got.push(r);
            }
            let k = offsets.iter().rposition(|&o| o <= cut).unwrap();
            prop_assert_eq!(&got, &records[..k].to_vec(), "cut {}", cut);
            if offsets.contains(&cut) {
                prop_assert_eq!(reader.cut(), None, "cut {} is a record boundary", cut);
            } else {
                prop_assert_eq!(
                    reader.cut(),
                    Some(holoface_protocol::recording::Cut { record_index: k as u64, offset: offsets[k] as u64 }),
                    "cut {}", cut
                );
            }
        }
    }

    #[test]
    fn every_bit_flip_in_a_record_is_detected(header in recording_header(), records in prop::collection::vec(frame_record(), 1..3)) {
        let file = encode_file(&header, &records);
        let header_len = header.encode().unwrap().len();
        let offsets = record_offsets(header_len, &records);
        for k in 0..records.len() {
            // The CRC field and the body of record k (not its length prefix).
            for byte in offsets[k] + 4..offsets[k + 1] {
                for bit in 0..8 {
                    let mut v = file.clone();
                    v[byte] ^= 1 << bit;
                    let res = read_all(&v);
                    match res {
                        Err(RecordingError::Corrupt { record_index, offset }) => {
                            prop_assert_eq!(record_index, k as u64);
                            prop_assert_eq!(offset, offsets[k] as u64);
                        }
                        other => prop_assert!(false, "byte {} bit {}: {:?}", byte, bit, other),
                    }
                }
            }
        }
        // Flips in the header body or its CRC are caught by the header CRC.
        for byte in 16..header_len {
            let mut v = file.clone();
            v[byte] ^= 0x01;
            let is_corrupt = matches!(read_all(&v), Err(RecordingError::HeaderCorrupt));
            prop_assert!(is_corrupt);
        }
    }

    #[test]
    fn any_bit_flip_in_a_file_never_panics(header in recording_header(), records in prop::collection::vec(frame_record(), 1..3)) {
        let file = encode_file(&header, &records);
        for bit in 0..file.len().min(4096) * 8 {
            let mut v = file.clone();
            v[bit / 8] ^= 1 << (bit % 8);
            let _ = read_all(&v);
        }
    }

    #[test]
    fn record_body_bit_flips_never_panic(record in frame_record()) {
        let mut body = BytesMut::new();
        record.encode_body(&mut body).unwrap();
        for bit in 0..body.len() * 8 {
            let mut v = body.to_vec();
            v[bit / 8] ^= 1 << (bit % 8);
            let _ = FrameRecord::decode_body(Bytes::from(v));
        }
        for i in 0..body.len() {
            prop_assert!(FrameRecord::decode_body(body.clone().freeze().slice(..i)).is_err());
        }
    }
}

#[test]
fn encode_never_writes_what_decode_refuses() {
    // Boundary values: exactly at each limit encodes; one past it does not.
    let at_limit = Message::ClientHello(ClientHello {
        version: 1,
        token: "t".repeat(MAX_TOKEN_LEN),
        client_name: "n".repeat(MAX_NAME_LEN),
        encodings: vec![CropEncoding::Raw; MAX_ENCODINGS],
        max_in_flight: 1,
    });
    assert_eq!(Message::decode(encode(&at_limit)).unwrap(), at_limit);
    let Message::ClientHello(mut over) = at_limit else {
        unreachable!()
    };
    over.encodings.push(CropEncoding::Png);
    assert!(Message::from(over).encode(&mut BytesMut::new()).is_err());

    let biggest = Message::FrameRequest(FrameRequest {
        track_id: 0,
        frame_id: u64::MAX,
        captured_at_us: u64::MAX,
        deadline_ms: u16::MAX,
        crop: Crop {
            encoding: CropEncoding::Png,
            width: MAX_CROP_DIM,
            height: MAX_CROP_DIM,
            data: vec![0xab; holoface_protocol::limits::MAX_ENCODED_CROP_LEN].into(),
        },
    });
    let mut framed = BytesMut::new();
    encode_framed(&biggest, &mut framed).unwrap();
    assert!(framed.len() - 4 <= MAX_MESSAGE_LEN);
    assert_eq!(decode_framed(&mut framed).unwrap(), Some(biggest));
}
