//! The message codec against the RFCs: byte-exact example encodings (RFC 7252 §2.2,
//! Appendix A, §3; RFC 7959 §3), every malformed-input rule with its reaction, typed
//! options, and proptest round trips.

use coap::msg::option::{decode_uint, encode_uint};
use coap::msg::{DecodeErrorKind, Message, MessageView, Reaction};
use coap::{BlockOpt, Code, ContentFormat, OptionNumber, Options, Token, Type};
use proptest::prelude::*;

/// A message from its parts.
fn msg(
    ty: Type,
    code: Code,
    mid: u16,
    token: &[u8],
    options: &[(OptionNumber, &[u8])],
    payload: &[u8],
) -> Message {
    let mut opts = Options::new();
    for (number, value) in options {
        opts.push(*number, *value);
    }
    Message {
        ty,
        code,
        message_id: mid,
        token: Token::new(token).unwrap(),
        options: opts,
        payload: payload.to_vec().into(),
    }
}

/// `bytes` decodes to `expected`, `expected` encodes to exactly `bytes`, and
/// `encoded_len` is exact.
#[track_caller]
fn assert_wire(expected: &Message, bytes: &[u8]) {
    let decoded = Message::decode(bytes).unwrap();
    assert_eq!(&decoded, expected);
    assert_eq!(expected.encode(), bytes);
    assert_eq!(expected.encoded_len(), bytes.len());
    let view = MessageView::new_checked(bytes).unwrap();
    assert_eq!(view.options().count(), expected.options.len());
}

/// `bytes` fails to decode with `kind`, and the endpoint's reaction is `reaction`.
#[track_caller]
fn assert_malformed(bytes: &[u8], kind: DecodeErrorKind, reaction: Reaction) {
    let err = Message::decode(bytes).unwrap_err();
    assert_eq!(err.kind, kind, "{bytes:02x?}");
    assert_eq!(Reaction::from(&err), reaction, "{bytes:02x?}");
    assert_eq!(MessageView::new_checked(bytes).unwrap_err(), err);
}

fn cat(parts: &[&[u8]]) -> Vec<u8> {
    parts.concat()
}

// ------------------------------------------------------------------ RFC example encodings

#[test]
fn rfc7252_appendix_a_fig16_con_get_piggybacked_2_05() {
    let req = msg(
        Type::Con,
        Code::GET,
        0x7d34,
        &[],
        &[(OptionNumber::URI_PATH, b"temperature")],
        &[],
    );
    assert_wire(
        &req,
        &cat(&[&[0x40, 0x01, 0x7d, 0x34, 0xbb], b"temperature"]),
    );
    let bytes = req.encode();
    let first = MessageView::new_checked(&bytes).unwrap().options().next();
    assert_eq!(first, Some((OptionNumber::URI_PATH, &b"temperature"[..])));

    let resp = msg(Type::Ack, Code::CONTENT, 0x7d34, &[], &[], b"22.3 C");
    assert_wire(&resp, &cat(&[&[0x60, 0x45, 0x7d, 0x34, 0xff], b"22.3 C"]));
}

#[test]
fn rfc7252_appendix_a_fig17_token_and_4_04_piggybacked() {
    let req = msg(
        Type::Con,
        Code::GET,
        0x7d35,
        &[0x20],
        &[(OptionNumber::URI_PATH, b"temperature")],
        &[],
    );
    assert_wire(
        &req,
        &cat(&[&[0x41, 0x01, 0x7d, 0x35, 0x20, 0xbb], b"temperature"]),
    );
    let resp = msg(
        Type::Ack,
        Code::NOT_FOUND,
        0x7d35,
        &[0x20],
        &[],
        b"Not found",
    );
    assert_wire(
        &resp,
        &cat(&[&[0x61, 0x84, 0x7d, 0x35, 0x20, 0xff], b"Not found"]),
    );
}

#[test]
fn rfc7252_2_2_separate_response_empty_ack_then_con_2_05() {
    let empty_ack = Message::empty(Type::Ack, 0x7a10);
    assert_wire(&empty_ack, &[0x60, 0x00, 0x7a, 0x10]);
    let resp = msg(Type::Con, Code::CONTENT, 0x23bb, &[0x23], &[], b"22.5 C");
    assert_wire(
        &resp,
        &cat(&[&[0x41, 0x45, 0x23, 0xbb, 0x23, 0xff], b"22.5 C"]),
    );
    let final_ack = Message::empty(Type::Ack, 0x23bb);
    assert_wire(&final_ack, &[0x60, 0x00, 0x23, 0xbb]);
}

#[test]
fn rfc7252_2_1_non_request_and_non_response() {
    let req = msg(
        Type::Non,
        Code::GET,
        0x7d40,
        &[0x74],
        &[(OptionNumber::URI_PATH, b"temperature")],
        &[],
    );
    assert_wire(
        &req,
        &cat(&[&[0x51, 0x01, 0x7d, 0x40, 0x74, 0xbb], b"temperature"]),
    );
    let resp = msg(Type::Non, Code::CONTENT, 0xad7d, &[0x74], &[], b"22.3 C");
    assert_wire(
        &resp,
        &cat(&[&[0x51, 0x45, 0xad, 0x7d, 0x74, 0xff], b"22.3 C"]),
    );
}

#[test]
fn rfc7252_4_3_ping_and_reset_are_four_bytes() {
    assert_wire(
        &Message::empty(Type::Con, 0x1234),
        &[0x40, 0x00, 0x12, 0x34],
    );
    assert_wire(
        &Message::empty(Type::Rst, 0x1234),
        &[0x70, 0x00, 0x12, 0x34],
    );
}

#[test]
fn rfc7252_3_empty_token_and_8_byte_token() {
    let empty = msg(Type::Con, Code::GET, 1, &[], &[], &[]);
    assert_wire(&empty, &[0x40, 0x01, 0x00, 0x01]);
    assert!(
        Message::decode(&[0x40, 0x01, 0x00, 0x01])
            .unwrap()
            .token
            .is_empty()
    );

    let t = [1, 2, 3, 4, 5, 6, 7, 8];
    let full = msg(Type::Con, Code::GET, 1, &t, &[], &[]);
    assert_wire(&full, &cat(&[&[0x48, 0x01, 0x00, 0x01], &t]));
    assert_eq!(Message::decode(&full.encode()).unwrap().token.as_bytes(), t);
    assert_eq!(Token::new(&[0; 9]), None, "a token holds at most 8 bytes");
}

#[test]
fn rfc7252_3_payload_marker_precedes_payload() {
    let m = msg(
        Type::Con,
        Code::POST,
        2,
        &[],
        &[(OptionNumber::CONTENT_FORMAT, &[50])],
        b"{}",
    );
    assert_wire(&m, &[0x40, 0x02, 0x00, 0x02, 0xc1, 0x32, 0xff, b'{', b'}']);
    // Without options the marker follows the token directly; without payload there is none.
    let no_payload = msg(Type::Con, Code::POST, 2, &[], &[], &[]);
    assert_eq!(no_payload.encode(), [0x40, 0x02, 0x00, 0x02]);
    let view = MessageView::new_checked(&[0x40, 0x02, 0x00, 0x02, 0xff, 0x00]).unwrap();
    assert_eq!(view.payload(), [0x00]);
    assert_eq!(view.options().count(), 0);
}

#[test]
fn rfc7252_3_1_option_delta_extended_13() {
    // Size1 (60) alone: delta 60 = 13 + 47.
    let m = msg(
        Type::Con,
        Code::PUT,
        3,
        &[],
        &[(OptionNumber::SIZE1, &[0x0d, 0xac])],
        &[],
    );
    assert_wire(&m, &[0x40, 0x03, 0x00, 0x03, 0xd2, 0x2f, 0x0d, 0xac]);
    // Echo (252) after Uri-Path (11): delta 241 = 13 + 228.
    let m = msg(
        Type::Con,
        Code::GET,
        3,
        &[],
        &[
            (OptionNumber::URI_PATH, b"a"),
            (OptionNumber::ECHO, &[9; 4]),
        ],
        &[],
    );
    assert_wire(
        &m,
        &[0x40, 0x01, 0x00, 0x03, 0xb1, b'a', 0xd4, 0xe4, 9, 9, 9, 9],
    );
}

#[test]
fn rfc7252_3_1_option_delta_extended_14() {
    // Request-Tag (292): delta 292 = 269 + 0x0017.
    let m = msg(
        Type::Con,
        Code::POST,
        4,
        &[],
        &[(OptionNumber::REQUEST_TAG, &[0xab])],
        &[],
    );
    assert_wire(&m, &[0x40, 0x02, 0x00, 0x04, 0xe1, 0x00, 0x17, 0xab]);
    // An unknown critical option 2051 after Request-Tag: delta 1759 = 269 + 0x05d2.
    let m = msg(
        Type::Con,
        Code::POST,
        4,
        &[],
        &[
            (OptionNumber::REQUEST_TAG, &[]),
            (OptionNumber(2051), &[0x01]),
        ],
        &[],
    );
    assert_wire(
        &m,
        &[
            0x40, 0x02, 0x00, 0x04, 0xe0, 0x00, 0x17, 0xe1, 0x05, 0xd2, 0x01,
        ],
    );
}

#[test]
fn rfc7252_3_1_option_delta_boundaries_12_13_268_269_65535() {
    for (number, header) in [
        (12u16, &[0xc0][..]),
        (13, &[0xd0, 0x00]),
        (268, &[0xd0, 0xff]),
        (269, &[0xe0, 0x00, 0x00]),
        (65535, &[0xe0, 0xfe, 0xf2]),
    ] {
        let m = msg(
            Type::Non,
            Code::GET,
            5,
            &[],
            &[(OptionNumber(number), &[])],
            &[],
        );
        assert_wire(&m, &cat(&[&[0x50, 0x01, 0x00, 0x05], header]));
    }
}

#[test]
fn rfc7252_3_1_option_length_extended_13() {
    // A 13-byte Uri-Path segment: length nibble 13, extension 0; 268 bytes: extension 255.
    for (len, header) in [(13usize, [0xbd, 0x00]), (268, [0xbd, 0xff])] {
        let seg = vec![b's'; len];
        let m = msg(
            Type::Con,
            Code::GET,
            6,
            &[],
            &[(OptionNumber::URI_PATH, &seg)],
            &[],
        );
        assert_wire(&m, &cat(&[&[0x40, 0x01, 0x00, 0x06], &header, &seg]));
    }
}

#[test]
fn rfc7252_3_1_option_length_extended_14_proxy_uri_300_bytes() {
    // Proxy-Uri (35): delta 35 = 13 + 22, length 300 = 269 + 0x001f.
    let uri = cat(&[b"coap://example.invalid/", &[b'x'; 277]]);
    assert_eq!(uri.len(), 300);
    let m = msg(
        Type::Con,
        Code::GET,
        7,
        &[],
        &[(OptionNumber::PROXY_URI, &uri)],
        &[],
    );
    assert_wire(
        &m,
        &cat(&[&[0x40, 0x01, 0x00, 0x07, 0xde, 0x16, 0x00, 0x1f], &uri]),
    );
    assert!(OptionNumber::PROXY_URI.accepts_len(300));
}

#[test]
fn rfc7959_3_1_fig2_block2_get_exchange() {
    // CON [MID=1234] GET /status -> ACK 2.05 Block2 0/1/128; then block 1 and block 2.
    let req0 = msg(
        Type::Con,
        Code::GET,
        1234,
        &[],
        &[(OptionNumber::URI_PATH, b"status")],
        &[],
    );
    assert_wire(&req0, &cat(&[&[0x40, 0x01, 0x04, 0xd2, 0xb6], b"status"]));
    let body = [b'a'; 128];
    let resp0 = msg(
        Type::Ack,
        Code::CONTENT,
        1234,
        &[],
        &[(OptionNumber::BLOCK2, &[0x0b])],
        &body,
    );
    assert_wire(
        &resp0,
        &cat(&[&[0x60, 0x45, 0x04, 0xd2, 0xd1, 0x0a, 0x0b, 0xff], &body]),
    );
    assert_eq!(
        resp0.options.block2(),
        Some(BlockOpt {
            num: 0,
            more: true,
            szx: 3
        })
    );
    let req1 = msg(
        Type::Con,
        Code::GET,
        1235,
        &[],
        &[
            (OptionNumber::URI_PATH, b"status"),
            (OptionNumber::BLOCK2, &[0x13]),
        ],
        &[],
    );
    assert_wire(
        &req1,
        &cat(&[&[0x40, 0x01, 0x04, 0xd3, 0xb6], b"status", &[0xc1, 0x13]]),
    );
    let last = BlockOpt::decode(&[0x23]).unwrap();
    assert_eq!((last.num, last.more, last.size()), (2, false, 128));
}

#[test]
fn rfc7959_3_2_block1_put_with_size1_and_2_31_continue() {
    // CON [MID=1234] PUT /options Block1 0/1/128 Size1 300 -> ACK 2.31 Block1 0/1/128.
    let body = [b'o'; 128];
    let req = msg(
        Type::Con,
        Code::PUT,
        1234,
        &[],
        &[
            (OptionNumber::URI_PATH, b"options"),
            (OptionNumber::BLOCK1, &[0x0b]),
            (OptionNumber::SIZE1, &[0x01, 0x2c]),
        ],
        &body,
    );
    let bytes = cat(&[
        &[0x40, 0x03, 0x04, 0xd2, 0xb7],
        b"options",
        // Block1 (27): delta 16 = 13 + 3. Size1 (60): delta 33 = 13 + 20.
        &[0xd1, 0x03, 0x0b, 0xd2, 0x14, 0x01, 0x2c, 0xff],
        &body,
    ]);
    assert_wire(&req, &bytes);
    assert_eq!(req.options.uint(OptionNumber::SIZE1), Some(300));

    let cont = msg(
        Type::Ack,
        Code::CONTINUE,
        1234,
        &[],
        &[(OptionNumber::BLOCK1, &[0x0b])],
        &[],
    );
    assert_wire(&cont, &[0x60, 0x5f, 0x04, 0xd2, 0xd1, 0x0e, 0x0b]);
    assert_eq!(Code::CONTINUE, Code::new(2, 31));
}

#[test]
fn rfc7959_4_size2_of_a_10_mb_body_and_4_13_with_size1() {
    let m = msg(
        Type::Ack,
        Code::CONTENT,
        9,
        &[],
        &[
            (OptionNumber::BLOCK2, &[0x0e]),
            (OptionNumber::SIZE2, &encode_uint(10_032_012)),
        ],
        &[0; 1024],
    );
    let bytes = m.encode();
    assert_eq!(
        bytes[4..12],
        [0xd1, 0x0a, 0x0e, 0x53, 0x99, 0x13, 0x8c, 0xff]
    );
    assert_wire(&m, &bytes);
    assert_eq!(m.options.uint(OptionNumber::SIZE2), Some(10_032_012));

    let too_large = msg(
        Type::Ack,
        Code::REQUEST_ENTITY_TOO_LARGE,
        10,
        &[],
        &[(OptionNumber::SIZE1, &encode_uint(3500))],
        &[],
    );
    assert_wire(
        &too_large,
        &[0x60, 0x8d, 0x00, 0x0a, 0xd2, 0x2f, 0x0d, 0xac],
    );
}

// ------------------------------------------------------------------ malformed inputs

#[test]
fn rfc7252_3_shorter_than_header_is_dropped() {
    for len in 0..=3 {
        assert_malformed(
            &[0x40, 0x01, 0x00][..len],
            DecodeErrorKind::TooShort,
            Reaction::Drop,
        );
    }
}

#[test]
fn rfc7252_3_version_other_than_1_is_silently_ignored() {
    for b0 in [0x00, 0x80, 0xc0, 0x80 | 0x08] {
        assert_malformed(
            &[b0, 0x01, 0x12, 0x34],
            DecodeErrorKind::Version,
            Reaction::Drop,
        );
    }
}

#[test]
fn rfc7252_3_token_length_9_to_15_is_a_format_error() {
    for tkl in 9..=15u8 {
        let mut con = vec![0x40 | tkl, 0x01, 0x12, 0x34];
        con.extend_from_slice(&[0xaa; 15]);
        assert_malformed(&con, DecodeErrorKind::TokenLength, Reaction::Reset(0x1234));
        // ACK and RST are never answered with a Reset (RFC 7252 §4.2).
        let ack = [0x60 | tkl, 0x45, 0x12, 0x34];
        assert_malformed(&ack, DecodeErrorKind::TokenLength, Reaction::Drop);
    }
}

#[test]
fn rfc7252_4_3_non_format_error_may_be_reset() {
    assert_malformed(
        &[0x5a, 0x01, 0xbe, 0xef],
        DecodeErrorKind::TokenLength,
        Reaction::Reset(0xbeef),
    );
    assert_malformed(
        &[0x70, 0x20, 0xbe, 0xef],
        DecodeErrorKind::ReservedClass,
        Reaction::Drop,
    );
}

#[test]
fn rfc7252_3_truncated_token() {
    assert_malformed(
        &[0x44, 0x01, 0x00, 0x01, 0xaa, 0xbb],
        DecodeErrorKind::Truncated,
        Reaction::Reset(1),
    );
}

#[test]
fn rfc7252_3_1_truncated_option_value_and_extensions() {
    let cases: [&[u8]; 6] = [
        // Uri-Path of length 5 with 3 bytes.
        &[0x40, 0x01, 0x00, 0x01, 0xb5, b't', b'e', b'm'],
        // Delta nibble 13 without its extension byte.
        &[0x40, 0x01, 0x00, 0x01, 0xd0],
        // Delta nibble 14 with one of its two extension bytes.
        &[0x40, 0x01, 0x00, 0x01, 0xe0, 0x00],
        // Length nibble 13 without its extension byte.
        &[0x40, 0x01, 0x00, 0x01, 0x1d],
        // Length nibble 14 with one extension byte.
        &[0x40, 0x01, 0x00, 0x01, 0x1e, 0x00],
        // Length 13 + 2 = 15 bytes announced, 1 present.
        &[0x40, 0x01, 0x00, 0x01, 0xbd, 0x02, b'x'],
    ];
    for bytes in cases {
        assert_malformed(bytes, DecodeErrorKind::Truncated, Reaction::Reset(1));
    }
    // The error points at the option header.
    let err = Message::decode(&[0x40, 0x01, 0x00, 0x01, 0xb1, b'a', 0x15, b'x']).unwrap_err();
    assert_eq!((err.kind, err.offset), (DecodeErrorKind::Truncated, 6));
}

#[test]
fn rfc7252_3_1_nibble_15_in_delta_or_length_is_a_format_error() {
    // Delta 15 with a length that is not 15 (0xff is the payload marker).
    for byte in [0xf0, 0xf1, 0xfd, 0xfe] {
        assert_malformed(
            &[0x40, 0x01, 0x00, 0x01, byte, 0, 0, 0],
            DecodeErrorKind::ReservedNibble,
            Reaction::Reset(1),
        );
    }
    // Length 15.
    for byte in [0x0f, 0xbf, 0xdf] {
        assert_malformed(
            &[0x50, 0x01, 0x00, 0x01, byte, 0, 0, 0],
            DecodeErrorKind::ReservedNibble,
            Reaction::Reset(1),
        );
    }
}

#[test]
fn rfc7252_3_payload_marker_with_empty_payload_is_a_format_error() {
    assert_malformed(
        &[0x40, 0x01, 0x00, 0x01, 0xff],
        DecodeErrorKind::EmptyPayload,
        Reaction::Reset(1),
    );
    assert_malformed(
        &[0x41, 0x45, 0x00, 0x01, 0x71, 0xc1, 0x00, 0xff],
        DecodeErrorKind::EmptyPayload,
        Reaction::Reset(1),
    );
    assert_malformed(
        &[0x60, 0x45, 0x00, 0x01, 0xff],
        DecodeErrorKind::EmptyPayload,
        Reaction::Drop,
    );
}

#[test]
fn rfc7252_4_1_empty_message_with_token_options_or_payload_is_a_format_error() {
    let cases: [&[u8]; 4] = [
        &[0x41, 0x00, 0x00, 0x07, 0xaa],
        &[0x40, 0x00, 0x00, 0x07, 0xb1, b'a'],
        &[0x40, 0x00, 0x00, 0x07, 0xff, 0x01],
        // A lone byte after the header is an option header with delta 0 and length 0.
        &[0x40, 0x00, 0x00, 0x07, 0x00],
    ];
    for bytes in cases {
        assert_malformed(bytes, DecodeErrorKind::EmptyWithContent, Reaction::Reset(7));
    }
    // An empty ACK or RST with content is silently ignored.
    assert_malformed(
        &[0x61, 0x00, 0x00, 0x07, 0xaa],
        DecodeErrorKind::EmptyWithContent,
        Reaction::Drop,
    );
    assert_malformed(
        &[0x70, 0x00, 0x00, 0x07, 0xff, 0x01],
        DecodeErrorKind::EmptyWithContent,
        Reaction::Drop,
    );
}

#[test]
fn rfc7252_12_1_reserved_code_classes_1_6_7() {
    for class in [1u8, 6, 7] {
        for detail in [0u8, 1, 31] {
            let code = Code::new(class, detail).0;
            assert_malformed(
                &[0x40, code, 0x00, 0x08],
                DecodeErrorKind::ReservedClass,
                Reaction::Reset(8),
            );
        }
    }
    // Classes 0 and 2-5 decode.
    for class in [0u8, 2, 3, 4, 5] {
        let code = Code::new(class, if class == 0 { 0 } else { 1 });
        assert_eq!(Message::decode(&[0x40, code.0, 0, 8]).unwrap().code, code);
    }
}

#[test]
fn rfc7252_3_1_option_number_past_65535_is_a_format_error() {
    // One delta of 269 + 65535.
    assert_malformed(
        &[0x40, 0x01, 0x00, 0x09, 0xe0, 0xff, 0xff],
        DecodeErrorKind::OptionNumber,
        Reaction::Reset(9),
    );
    // 65535, then a delta of 1.
    assert_malformed(
        &[0x40, 0x01, 0x00, 0x09, 0xe0, 0xfe, 0xf2, 0x10],
        DecodeErrorKind::OptionNumber,
        Reaction::Reset(9),
    );
    // 65535 itself is fine.
    let m = Message::decode(&[0x40, 0x01, 0x00, 0x09, 0xe0, 0xfe, 0xf2]).unwrap();
    assert_eq!(m.options.iter().next().unwrap().number, OptionNumber(65535));
}

// ------------------------------------------------------------------ typed options

#[test]
fn rfc7959_2_2_block_options_through_the_wire() {
    for (number, b) in [
        (
            OptionNumber::BLOCK1,
            BlockOpt {
                num: 0,
                more: false,
                szx: 0,
            },
        ),
        (
            OptionNumber::BLOCK2,
            BlockOpt {
                num: 9796,
                more: true,
                szx: 6,
            },
        ),
        (
            OptionNumber::BLOCK1,
            BlockOpt {
                num: BlockOpt::MAX_NUM,
                more: false,
                szx: 2,
            },
        ),
    ] {
        let mut m = Message::empty(Type::Con, 1);
        m.code = Code::GET;
        m.options.set_block(number, b);
        let back = Message::decode(&m.encode()).unwrap();
        assert_eq!(back.options.block(number), Some(b));
    }
    // num 0 / more 0 / szx 0 is the zero-length value (RFC 7252 §3.2 minimal uint).
    assert_eq!(
        BlockOpt {
            num: 0,
            more: false,
            szx: 0
        }
        .encode(),
        Vec::<u8>::new()
    );
    assert_eq!(BlockOpt::decode(&[0x0f]), None, "SZX 7 is BERT, not UDP");
    assert_eq!(
        BlockOpt::decode(&[0, 0, 0, 0x10]),
        None,
        "more than 3 bytes"
    );
}

#[test]
fn rfc9177_4_q_block1_19_and_q_block2_31_are_known_critical() {
    assert_eq!(OptionNumber::Q_BLOCK1, OptionNumber(19));
    assert_eq!(OptionNumber::Q_BLOCK2, OptionNumber(31));
    for n in [OptionNumber::Q_BLOCK1, OptionNumber::Q_BLOCK2] {
        assert!(n.is_critical());
        assert!(n.info().is_some());
    }
    assert_eq!(OptionNumber::Q_BLOCK1.to_string(), "Q-Block1");
    assert_eq!(OptionNumber::Q_BLOCK2.to_string(), "Q-Block2");
    let mut o = Options::new();
    o.set_block(
        OptionNumber::Q_BLOCK2,
        BlockOpt {
            num: 3,
            more: true,
            szx: 6,
        },
    );
    assert_eq!(o.first_bad_critical(), None);
    assert_eq!(o.block(OptionNumber::Q_BLOCK2).map(|b| b.num), Some(3));
}

#[test]
fn rfc7252_5_10_3_content_format_and_accept_uints() {
    for (cf, value) in [
        (ContentFormat::TEXT_PLAIN, &[][..]),
        (ContentFormat::LINK_FORMAT, &[40]),
        (ContentFormat::JSON, &[50]),
        (ContentFormat::COAP_GROUP_JSON, &[0x01, 0x00]),
    ] {
        let mut o = Options::new();
        o.set_uint(OptionNumber::CONTENT_FORMAT, u32::from(cf.0));
        o.set_uint(OptionNumber::ACCEPT, u32::from(cf.0));
        assert_eq!(o.first(OptionNumber::CONTENT_FORMAT), Some(value));
        let m = Message {
            options: o,
            ..msg(Type::Con, Code::GET, 1, &[], &[], &[])
        };
        let back = Message::decode(&m.encode()).unwrap();
        assert_eq!(back.options.content_format(), Some(cf));
        assert_eq!(back.options.accept(), Some(cf));
    }
    // A 3-byte value does not fit a content format.
    let mut o = Options::new();
    o.set(OptionNumber::CONTENT_FORMAT, vec![1, 0, 0]);
    assert_eq!(o.content_format(), None);
}

#[test]
fn rfc7252_3_2_uint_options_size1_size2_observe_max_age() {
    for (number, v) in [
        (OptionNumber::SIZE1, 0u32),
        (OptionNumber::SIZE1, 3500),
        (OptionNumber::SIZE2, 10_032_012),
        (OptionNumber::SIZE2, u32::MAX),
        (OptionNumber::OBSERVE, 0xff_ffff),
        (OptionNumber::MAX_AGE, 60),
    ] {
        let mut o = Options::new();
        o.set_uint(number, v);
        let value = o.first(number).unwrap();
        assert!(value.first() != Some(&0), "no leading zero bytes");
        assert!(number.accepts_len(value.len()));
        assert_eq!(decode_uint(value), Some(v));
        let m = Message {
            options: o,
            ..msg(Type::Non, Code::CONTENT, 1, &[1], &[], &[])
        };
        assert_eq!(
            Message::decode(&m.encode()).unwrap().options.uint(number),
            Some(v)
        );
    }
}

#[test]
fn rfc7252_5_10_6_etag_repeatable_and_first_wins() {
    let m = msg(
        Type::Con,
        Code::GET,
        1,
        &[],
        &[(OptionNumber::ETAG, &[1, 2]), (OptionNumber::ETAG, &[3])],
        &[],
    );
    assert_wire(&m, &[0x40, 0x01, 0x00, 0x01, 0x42, 1, 2, 0x01, 3]);
    let back = Message::decode(&m.encode()).unwrap();
    assert_eq!(back.options.etag(), Some(&[1u8, 2][..]));
    assert_eq!(back.options.values(OptionNumber::ETAG).count(), 2);
    assert!(!OptionNumber::ETAG.accepts_len(0) && !OptionNumber::ETAG.accepts_len(9));
}

#[test]
fn rfc9175_2_2_echo_and_3_2_request_tag() {
    assert_eq!(OptionNumber::ECHO, OptionNumber(252));
    assert_eq!(OptionNumber::REQUEST_TAG, OptionNumber(292));
    assert!(!OptionNumber::ECHO.is_critical() && !OptionNumber::ECHO.is_unsafe());
    assert!(OptionNumber::ECHO.is_no_cache_key());
    assert!(!OptionNumber::REQUEST_TAG.is_critical());
    assert!(OptionNumber::ECHO.accepts_len(40) && !OptionNumber::ECHO.accepts_len(41));
    // Request-Tag is repeatable and may be empty.
    let m = msg(
        Type::Con,
        Code::POST,
        1,
        &[],
        &[
            (OptionNumber::ECHO, &[7; 8]),
            (OptionNumber::REQUEST_TAG, &[]),
            (OptionNumber::REQUEST_TAG, &[1]),
        ],
        &[],
    );
    let back = Message::decode(&m.encode()).unwrap();
    assert_eq!(back, m);
    let tags: Vec<&[u8]> = back.options.values(OptionNumber::REQUEST_TAG).collect();
    assert_eq!(tags, [&[][..], &[1][..]]);
    assert_eq!(back.options.first_bad_critical(), None);
}

#[test]
fn rfc7252_5_4_1_unknown_options_kept_through_decode_and_encode() {
    let bytes = [
        0x40, 0x01, 0x00, 0x01, //
        0xb1, b'a', // Uri-Path 11
        0xe1, 0x06, 0xea, 0x05, // 2050 (elective, unknown)
        0x11, 0x06, // 2051 (critical, unknown)
        0xe2, 0xf0, 0xf0, 0xaa, 0xbb, // 64000 (unknown)
    ];
    let m = Message::decode(&bytes).unwrap();
    let numbers: Vec<u16> = m.options.iter().map(|o| o.number.0).collect();
    assert_eq!(numbers, [11, 2050, 2051, 64000]);
    for n in [2050, 2051, 64000] {
        assert!(OptionNumber(n).info().is_none());
    }
    assert_eq!(m.encode(), bytes);
    assert_eq!(m.options.first_bad_critical(), Some(OptionNumber(2051)));
}

#[test]
fn rfc7252_5_4_5_repeated_options_keep_their_order_on_the_wire() {
    let bytes = cat(&[
        &[0x40, 0x01, 0x00, 0x01],
        &[0xb4],
        b"cams",
        &[0x0b],
        b"pointclouds",
        &[0x04],
        b"last",
    ]);
    let m = Message::decode(&bytes).unwrap();
    assert_eq!(m.options.path_string(), "/cams/pointclouds/last");
    assert_eq!(m.encode(), bytes);
}

// ------------------------------------------------------------------ proptest

fn arb_type() -> impl Strategy<Value = Type> {
    prop_oneof![
        Just(Type::Con),
        Just(Type::Non),
        Just(Type::Ack),
        Just(Type::Rst)
    ]
}

/// Option numbers biased towards registered ones and to repeats, over the full range.
fn arb_number() -> impl Strategy<Value = OptionNumber> {
    prop_oneof![
        3 => prop::sample::select(vec![1u16, 4, 6, 11, 12, 15, 19, 23, 27, 28, 31, 35, 60, 252, 292]),
        1 => 0u16..=300,
        1 => any::<u16>(),
    ]
    .prop_map(OptionNumber)
}

fn arb_options() -> impl Strategy<Value = Options> {
    prop::collection::vec(
        (
            arb_number(),
            prop_oneof![
                4 => prop::collection::vec(any::<u8>(), 0..16),
                1 => prop::collection::vec(any::<u8>(), 0..300),
            ],
        ),
        0..12,
    )
    .prop_map(|list| {
        let mut o = Options::new();
        for (n, v) in list {
            o.push(n, v);
        }
        o
    })
}

/// Any valid message: an Empty message (0.00) has no token, options or payload.
fn arb_message() -> impl Strategy<Value = Message> {
    let code = prop_oneof![
        1 => Just(Code::EMPTY),
        3 => (1u8..32).prop_map(|d| Code::new(0, d)),
        3 => (2u8..=5, 0u8..32).prop_map(|(c, d)| Code::new(c, d)),
    ];
    (
        arb_type(),
        code,
        any::<u16>(),
        prop::collection::vec(any::<u8>(), 0..=8),
        arb_options(),
        prop::collection::vec(any::<u8>(), 0..1500),
    )
        .prop_map(|(ty, code, message_id, token, options, payload)| {
            if code.is_empty() {
                Message::empty(ty, message_id)
            } else {
                Message {
                    ty,
                    code,
                    message_id,
                    token: Token::new(&token).unwrap(),
                    options,
                    payload: payload.into(),
                }
            }
        })
}

/// Byte strings that look like CoAP often enough to reach the option parser.
fn arb_datagram() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        prop::collection::vec(any::<u8>(), 0..64),
        (
            0u8..=8,
            prop::sample::select(vec![0x01u8, 0x02, 0x45, 0x5f, 0x84, 0xa0]),
            prop::collection::vec(any::<u8>(), 0..400)
        )
            .prop_map(|(tkl, code, rest)| {
                let mut d = vec![0x40 | tkl, code, 0x12, 0x34];
                d.extend(rest);
                d
            }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn rfc7252_3_any_message_round_trips_exactly(m in arb_message()) {
        let bytes = m.encode();
        prop_assert_eq!(bytes.len(), m.encoded_len());
        let back = Message::decode(&bytes).unwrap();
        prop_assert_eq!(&back, &m);
        prop_assert_eq!(back.encode(), bytes);
    }

    #[test]
    fn rfc7252_3_any_bytes_never_panic_and_decoded_reencode_identically(data in arb_datagram()) {
        let view = MessageView::new_checked(&data);
        match Message::decode(&data) {
            Ok(m) => {
                let view = view.unwrap();
                prop_assert_eq!(view.payload(), &m.payload[..]);
                prop_assert_eq!(view.options().count(), m.options.len());
                // The wire format has one encoding per message.
                let bytes = m.encode();
                prop_assert_eq!(&bytes, &data);
                prop_assert_eq!(Message::decode(&bytes).unwrap(), m);
            }
            Err(e) => {
                prop_assert_eq!(view.unwrap_err(), e);
                let _ = Reaction::from(&e);
            }
        }
    }

    #[test]
    fn rfc7959_2_2_any_block_option_round_trips(
        num in 0..=BlockOpt::MAX_NUM,
        more in any::<bool>(),
        szx in 0u8..=6,
    ) {
        let b = BlockOpt { num, more, szx };
        let value = b.encode();
        prop_assert!(value.len() <= 3);
        prop_assert!(value.first() != Some(&0));
        prop_assert_eq!(BlockOpt::decode(&value), Some(b));
        prop_assert_eq!(b.offset(), num as usize * (16 << szx));
    }

    #[test]
    fn rfc7252_3_2_any_uint_round_trips_minimally(v in any::<u32>()) {
        let value = encode_uint(v);
        prop_assert!(value.first() != Some(&0));
        prop_assert_eq!(decode_uint(&value), Some(v));
    }
}
