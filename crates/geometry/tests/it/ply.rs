use geometry::{PlyError, Point3, PointCloud, decode_ply, encode_ply, write_ply};

fn cloud() -> PointCloud {
    PointCloud::from(vec![
        Point3::new(0.0, 0.0, 0.0),
        Point3::new(-1.5, 2.25, 0.125),
        Point3::new(f32::MAX, f32::MIN_POSITIVE, -0.0),
        Point3::new(0.1, 0.2, 0.3),
    ])
}

const HEADER_4: &str = "ply\nformat binary_little_endian 1.0\ncomment coapcam test\n\
                        element vertex 4\nproperty float x\nproperty float y\n\
                        property float z\nend_header\n";

#[test]
fn the_header_is_exactly_standard_and_the_data_is_little_endian_f32() {
    let bytes = encode_ply(&cloud().points, Some("coapcam test")).expect("encodes");
    assert_eq!(&bytes[..HEADER_4.len()], HEADER_4.as_bytes());
    let data = &bytes[HEADER_4.len()..];
    assert_eq!(data.len(), 4 * 12);
    assert_eq!(&data[12..16], &(-1.5f32).to_le_bytes());
    assert_eq!(&data[16..20], &2.25f32.to_le_bytes());
    assert_eq!(&data[44..48], &0.3f32.to_le_bytes());
}

#[test]
fn a_cloud_round_trips_bit_for_bit_with_and_without_comment() {
    for comment in [None, Some("frame 7 of 012345678901")] {
        let bytes = encode_ply(&cloud().points, comment).expect("encodes");
        let back = decode_ply(&bytes).expect("decodes");
        assert_eq!(back.len(), 4);
        for (a, b) in back.points.iter().zip(&cloud().points) {
            assert_eq!(a.coords.map(f32::to_bits), b.coords.map(f32::to_bits));
        }
    }
    let empty = encode_ply(&[], None).expect("encodes");
    assert!(decode_ply(&empty).expect("decodes").is_empty());
}

#[test]
fn write_ply_streams_into_any_writer() {
    let mut sink = std::io::Cursor::new(Vec::new());
    write_ply(&cloud().points, None, &mut sink).expect("writes");
    assert_eq!(
        sink.into_inner(),
        encode_ply(&cloud().points, None).expect("encodes")
    );
}

#[test]
fn a_comment_with_a_line_break_is_refused() {
    assert!(matches!(
        encode_ply(&cloud().points, Some("two\nlines")),
        Err(PlyError::InvalidComment)
    ));
    let long = "c".repeat(300);
    assert!(matches!(
        encode_ply(&cloud().points, Some(&long)),
        Err(PlyError::InvalidComment)
    ));
}

#[test]
fn a_vertex_count_that_does_not_match_the_data_is_refused() {
    let bytes = encode_ply(&cloud().points, None).expect("encodes");
    // One byte short, one byte long.
    for data in [
        &bytes[..bytes.len() - 1],
        &[bytes.as_slice(), &[0]].concat()[..],
    ] {
        assert!(matches!(
            decode_ply(data),
            Err(PlyError::LengthMismatch {
                declared: 4,
                stride: 12,
                ..
            })
        ));
    }
    // A count whose byte length overflows.
    let huge = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\nend_header\n",
        u64::MAX
    );
    assert!(matches!(
        decode_ply(huge.as_bytes()),
        Err(PlyError::LengthMismatch { .. })
    ));
}

#[test]
fn other_scalar_properties_are_skipped_and_doubles_are_read() {
    let header = "ply\r\nformat binary_little_endian 1.0\r\nobj_info scanner\r\n\
                  element vertex 2\r\nproperty uchar red\r\nproperty double z\r\n\
                  property float x\r\nproperty float32 y\r\nproperty short nx\r\nend_header\r\n";
    let mut bytes = header.as_bytes().to_vec();
    for (x, y, z) in [(1.0f32, 2.0f32, 3.0f64), (-4.0, 5.5, 0.25)] {
        bytes.push(200);
        bytes.extend_from_slice(&z.to_le_bytes());
        bytes.extend_from_slice(&x.to_le_bytes());
        bytes.extend_from_slice(&y.to_le_bytes());
        bytes.extend_from_slice(&7i16.to_le_bytes());
    }
    let cloud = decode_ply(&bytes).expect("decodes");
    assert_eq!(
        cloud.points,
        vec![Point3::new(1.0, 2.0, 3.0), Point3::new(-4.0, 5.5, 0.25)]
    );
}

#[test]
fn unsupported_files_are_refused_with_the_reason() {
    let body =
        "element vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    let ascii = format!("ply\nformat ascii 1.0\n{body}");
    assert!(matches!(
        decode_ply(ascii.as_bytes()),
        Err(PlyError::UnsupportedFormat { found }) if found == "ascii 1.0"
    ));
    let list = "ply\nformat binary_little_endian 1.0\nelement vertex 0\n\
                property list uchar int vertex_indices\nend_header\n";
    assert!(matches!(
        decode_ply(list.as_bytes()),
        Err(PlyError::UnsupportedProperty { .. })
    ));
    let no_z = "ply\nformat binary_little_endian 1.0\nelement vertex 0\n\
                property float x\nproperty float y\nproperty uchar z\nend_header\n";
    assert!(matches!(
        decode_ply(no_z.as_bytes()),
        Err(PlyError::MissingCoordinate { axis: 'z' })
    ));
    let face = format!("ply\nformat binary_little_endian 1.0\n{body}")
        .replace("end_header", "element face 0\nend_header");
    assert!(matches!(
        decode_ply(face.as_bytes()),
        Err(PlyError::BadHeader { line: 7, .. })
    ));
    assert!(matches!(decode_ply(b"PK\x03\x04"), Err(PlyError::NotPly)));
    let endless = format!("ply\n{}", "comment x\n".repeat(1000));
    assert!(matches!(
        decode_ply(endless.as_bytes()),
        Err(PlyError::HeaderTooLong)
    ));
}
