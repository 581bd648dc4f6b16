//! PNG and JPEG: color as 8-bit RGB(A) PNG or JPEG, depth as 16-bit grayscale PNG of the
//! raw units.

use image::codecs::jpeg::JpegEncoder;
use image::codecs::png::PngEncoder;
use image::{ExtendedColorType, ImageEncoder as _, ImageFormat};
use rgbd::{ColorFormat, ColorFrame, DepthFrame};

use image::RgbImage;

use super::codec::{ColorDecoder, DecodeError, Decoders, DepthImage, EncodeError, Subject};
use super::packet::{compact_pixels, depth_rows};

/// Quality of JPEG color images.
/// The JPEG quality when the request names none (`q=N` on a color resource).
pub const JPEG_QUALITY: u8 = 90;

fn image_error(format: &'static str) -> impl FnOnce(image::ImageError) -> EncodeError {
    move |source| EncodeError::Image { format, source }
}

/// The pixels as RGB (or RGBA when the frame has alpha), compact rows.
fn rgb_pixels(frame: &ColorFrame) -> (Vec<u8>, ExtendedColorType) {
    let (alpha, swap) = match frame.format {
        ColorFormat::Rgb8 => (false, false),
        ColorFormat::Bgr8 => (false, true),
        ColorFormat::Rgba8 => (true, false),
        ColorFormat::Bgra8 => (true, true),
    };
    let bpp = frame.format.bytes_per_pixel();
    let mut out = Vec::with_capacity(frame.width as usize * frame.height as usize * bpp);
    for row in compact_pixels(frame) {
        for px in row.chunks_exact(bpp) {
            let (r, b) = if swap { (px[2], px[0]) } else { (px[0], px[2]) };
            out.extend_from_slice(&[r, px[1], b]);
            if alpha {
                out.push(px[3]);
            }
        }
    }
    let ty = if alpha {
        ExtendedColorType::Rgba8
    } else {
        ExtendedColorType::Rgb8
    };
    (out, ty)
}

/// Color as an 8-bit RGB(A) PNG.
pub fn color_png(frame: &ColorFrame) -> Result<Vec<u8>, EncodeError> {
    let (pixels, ty) = rgb_pixels(frame);
    let mut out = Vec::new();
    PngEncoder::new(&mut out)
        .write_image(&pixels, frame.width, frame.height, ty)
        .map_err(image_error("PNG"))?;
    Ok(out)
}

/// Color as a JPEG of `quality` (1-100; alpha dropped).
pub fn color_jpeg(frame: &ColorFrame, quality: u8) -> Result<Vec<u8>, EncodeError> {
    let (pixels, ty) = rgb_pixels(frame);
    let rgb: Vec<u8> = if ty == ExtendedColorType::Rgba8 {
        pixels
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2]])
            .collect()
    } else {
        pixels
    };
    let mut out = Vec::new();
    JpegEncoder::new_with_quality(&mut out, quality)
        .write_image(&rgb, frame.width, frame.height, ExtendedColorType::Rgb8)
        .map_err(image_error("JPEG"))?;
    Ok(out)
}

/// Color as an 8-bit RGB image (alpha dropped), to draw on.
pub fn color_rgb(frame: &ColorFrame) -> RgbImage {
    let (pixels, ty) = rgb_pixels(frame);
    let (w, h) = (frame.width, frame.height);
    let image = if ty == ExtendedColorType::Rgba8 {
        image::RgbaImage::from_raw(w, h, pixels)
            .map(|i| image::DynamicImage::ImageRgba8(i).to_rgb8())
    } else {
        RgbImage::from_raw(w, h, pixels)
    };
    image.unwrap_or_default()
}

/// Color as 8-bit gray, converted as `image` converts an RGB image (the codes reader
/// reads gray).
pub fn color_gray(frame: &ColorFrame) -> image::GrayImage {
    let (pixels, ty) = rgb_pixels(frame);
    let (w, h) = (frame.width, frame.height);
    let image = if ty == ExtendedColorType::Rgba8 {
        image::RgbaImage::from_raw(w, h, pixels).map(image::DynamicImage::ImageRgba8)
    } else {
        RgbImage::from_raw(w, h, pixels).map(image::DynamicImage::ImageRgb8)
    };
    image.map(|i| i.to_luma8()).unwrap_or_default()
}

/// Depth as a 16-bit grayscale PNG of the raw units.
pub fn depth_png(frame: &DepthFrame) -> Result<Vec<u8>, EncodeError> {
    let mut pixels = Vec::with_capacity(frame.width as usize * frame.height as usize * 2);
    for row in depth_rows(frame) {
        for v in row {
            pixels.extend_from_slice(&v.to_ne_bytes());
        }
    }
    let mut out = Vec::new();
    PngEncoder::new(&mut out)
        .write_image(&pixels, frame.width, frame.height, ExtendedColorType::L16)
        .map_err(image_error("PNG"))?;
    Ok(out)
}

// ---- reading

/// A 16-bit grayscale PNG of raw depth units (the server's `image/png` depth).
pub fn depth_from_png(png: &[u8]) -> Result<DepthImage, DecodeError> {
    let image = image::load_from_memory_with_format(png, ImageFormat::Png).map_err(|source| {
        DecodeError::Image {
            what: "depth PNG",
            source,
        }
    })?;
    let image::DynamicImage::ImageLuma16(gray) = image else {
        return Err(DecodeError::DepthNotGray16);
    };
    Ok(DepthImage {
        width: gray.width(),
        height: gray.height(),
        timestamp_s: 0,
        depth_scale: 0.001,
        values: gray.into_raw(),
    })
}

// ---- the rows of the table

/// PNG's encoder: color and depth.
pub fn encode_png(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    match *subject {
        Subject::Color { frame, .. } => color_png(frame),
        Subject::Depth { frame, .. } => depth_png(frame),
        Subject::Cloud { .. } => Err(subject.not_served("PNG")),
    }
}

/// JPEG's encoder: color, at the subject's quality.
pub fn encode_jpeg(subject: &Subject<'_>) -> Result<Vec<u8>, EncodeError> {
    match *subject {
        Subject::Color { frame, quality, .. } => color_jpeg(frame, quality),
        _ => Err(subject.not_served("JPEG")),
    }
}

/// A PNG or JPEG color image as RGB.
fn color_from_image(body: &[u8]) -> Result<RgbImage, DecodeError> {
    let image = image::load_from_memory(body).map_err(|source| DecodeError::Image {
        what: "color image",
        source,
    })?;
    Ok(image.to_rgb8())
}

/// PNG read back: color and depth.
pub const PNG_DECODERS: Decoders = Decoders {
    color: Some(ColorDecoder::Image(color_from_image)),
    depth: Some(depth_from_png),
    cloud: None,
};

/// JPEG read back: color.
pub const JPEG_DECODERS: Decoders = Decoders {
    color: Some(ColorDecoder::Image(color_from_image)),
    ..Decoders::NONE
};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::repr::tests::color;

    #[test]
    fn images_encode() {
        let frame = color(ColorFormat::Bgra8, 4, 2, 16);
        assert!(color_png(&frame).is_ok_and(|p| p.starts_with(b"\x89PNG")));
        assert!(color_jpeg(&frame, 90).is_ok_and(|p| p.starts_with(&[0xff, 0xd8])));
    }
}
