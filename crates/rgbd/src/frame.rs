//! Color and depth frames as a camera delivers them.

use serde::{Deserialize, Serialize};

/// Pixel format of a color frame (the D415 color formats of thesis §3.3.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ColorFormat {
    /// 8-bit red, green, blue.
    #[serde(rename = "RGB8")]
    Rgb8,
    /// 8-bit blue, green, red.
    #[serde(rename = "BGR8")]
    Bgr8,
    /// 8-bit red, green, blue, alpha.
    #[serde(rename = "RGBA8")]
    Rgba8,
    /// 8-bit blue, green, red, alpha.
    #[serde(rename = "BGRA8")]
    Bgra8,
}

impl ColorFormat {
    /// Every color format, in the order of the thesis.
    pub const ALL: [Self; 4] = [Self::Rgb8, Self::Bgr8, Self::Rgba8, Self::Bgra8];

    /// The name librealsense and the JSON documents use ("RGB8", ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::Rgb8 => "RGB8",
            Self::Bgr8 => "BGR8",
            Self::Rgba8 => "RGBA8",
            Self::Bgra8 => "BGRA8",
        }
    }

    /// Parses a format name exactly as [`ColorFormat::name`] prints it.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Bytes per pixel (3 or 4).
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            Self::Rgb8 | Self::Bgr8 => 3,
            Self::Rgba8 | Self::Bgra8 => 4,
        }
    }

    /// Writes one opaque pixel given as red, green, blue into `out`
    /// (which holds exactly [`ColorFormat::bytes_per_pixel`] bytes).
    pub(crate) fn write_pixel(self, rgb: [u8; 3], out: &mut [u8]) {
        let [r, g, b] = rgb;
        match self {
            Self::Rgb8 => out.copy_from_slice(&[r, g, b]),
            Self::Bgr8 => out.copy_from_slice(&[b, g, r]),
            Self::Rgba8 => out.copy_from_slice(&[r, g, b, 255]),
            Self::Bgra8 => out.copy_from_slice(&[b, g, r, 255]),
        }
    }
}

/// Pixel format of a depth frame. The D415 delivers only Z16.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DepthFormat {
    /// 16-bit unsigned depth in units of the frame's depth scale; 0 = no depth.
    #[serde(rename = "Z16")]
    Z16,
}

impl DepthFormat {
    /// The name librealsense and the JSON documents use ("Z16").
    pub fn name(self) -> &'static str {
        match self {
            Self::Z16 => "Z16",
        }
    }

    /// Parses a format name exactly as [`DepthFormat::name`] prints it.
    pub fn from_name(name: &str) -> Option<Self> {
        (name == "Z16").then_some(Self::Z16)
    }
}

/// One color image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ColorFrame {
    /// Pixel format of `data`.
    pub format: ColorFormat,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Bytes from the start of one row to the next.
    pub stride: usize,
    /// Capture time in microseconds (since the UNIX epoch for grabbed frames).
    pub timestamp_us: u64,
    /// Frame counter of the color stream, starting at 1 and increasing by one per frame.
    pub frame_number: u64,
    /// Pixels, row-major, `stride * height` bytes.
    pub data: Vec<u8>,
}

impl ColorFrame {
    /// The red, green, blue value of pixel (`x`, `y`), whatever the format;
    /// `None` outside the image.
    pub fn rgb_at(&self, x: u32, y: u32) -> Option<[u8; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let bpp = self.format.bytes_per_pixel();
        let start = (y as usize)
            .checked_mul(self.stride)?
            .checked_add((x as usize).checked_mul(bpp)?)?;
        let px = self.data.get(start..start.checked_add(bpp)?)?;
        Some(match self.format {
            ColorFormat::Rgb8 | ColorFormat::Rgba8 => [px[0], px[1], px[2]],
            ColorFormat::Bgr8 | ColorFormat::Bgra8 => [px[2], px[1], px[0]],
        })
    }
}

/// One depth image in raw Z16 units.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthFrame {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Values from the start of one row to the next (in `u16`s, not bytes).
    pub stride: usize,
    /// Metres per raw unit (librealsense's depth units; 0.001 by default).
    pub depth_scale: f32,
    /// Capture time in microseconds (since the UNIX epoch for grabbed frames).
    pub timestamp_us: u64,
    /// Frame counter of the depth stream, starting at 1 and increasing by one per frame.
    pub frame_number: u64,
    /// Raw depth, row-major, `stride * height` values; 0 means no depth.
    pub data: Vec<u16>,
}

impl DepthFrame {
    /// The depth scale every D400 camera starts with: one millimetre per unit.
    pub const DEFAULT_DEPTH_SCALE: f32 = 0.001;

    /// Raw value at pixel (`x`, `y`); `None` outside the image.
    pub fn raw_at(&self, x: u32, y: u32) -> Option<u16> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let index = (y as usize)
            .checked_mul(self.stride)?
            .checked_add(x as usize)?;
        self.data.get(index).copied()
    }

    /// Depth in metres at pixel (`x`, `y`); `None` outside the image or where the
    /// camera measured nothing (raw 0).
    pub fn metres_at(&self, x: u32, y: u32) -> Option<f32> {
        self.raw_at(x, y)
            .filter(|&raw| raw != 0)
            .map(|raw| f32::from(raw) * self.depth_scale)
    }
}
