//! Shaded images of the tracer: per-pixel normal or ambient-occlusion shading of the protocol
//! camera's primary rays, as 8-bit RGB, with PNG encoding and decoding for `emc render` and
//! the reference-image test.
#![forbid(unsafe_code)]

use std::io::{BufWriter, Read, Write};

use glam::Vec3;

use crate::trace::intersect::Hit;
use crate::trace::workload::{ao_rays, facing_normal, tile_order};
use crate::trace::WideBvh;

/// How pixels are shaded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Shading {
    /// The facing geometric normal mapped to colour: `rgb = 255·(n/2 + 1/2)`.
    #[default]
    Normal,
    /// Grey level `255·(1 − occluded/4)` from the protocol's 4 AO rays of the pixel.
    Ao,
}

impl core::str::FromStr for Shading {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "normal" => Ok(Shading::Normal),
            "ao" => Ok(Shading::Ao),
            _ => Err(format!("unknown shading `{s}` (normal, ao)")),
        }
    }
}

/// Colour of a pixel whose ray misses.
pub const BACKGROUND: [u8; 3] = [24, 24, 32];

/// An 8-bit RGB image, rows top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `3·width·height` bytes, row-major RGB.
    pub rgb: Vec<u8>,
}

#[inline]
fn to_byte(x: f32) -> u8 {
    (x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// Shade the primary hits `hits` (tile order, as [`crate::trace::workload::primary_rays`]
/// makes them for a `w × h` image) of `rays`.
pub fn shade(
    bvh: &WideBvh,
    tris: &[[Vec3; 3]],
    rays: &[crate::trace::Ray],
    hits: &[Option<Hit>],
    (w, h): (u32, u32),
    diag: f64,
    shading: Shading,
) -> Image {
    use rayon::prelude::*;
    let order = tile_order(w, h);
    let colours: Vec<[u8; 3]> = (0..rays.len())
        .into_par_iter()
        .map(|i| {
            let Some(hit) = hits[i] else {
                return BACKGROUND;
            };
            match shading {
                Shading::Normal => {
                    let n = facing_normal(&tris[hit.prim as usize], rays[i].dir);
                    let c = n * 0.5 + Vec3::splat(0.5);
                    [to_byte(c.x), to_byte(c.y), to_byte(c.z)]
                }
                Shading::Ao => {
                    let ao = ao_rays(i as u32, &rays[i], &hit, tris, diag);
                    let occ = ao
                        .iter()
                        .filter(|r| {
                            crate::trace::traverse::occluded::<false>(
                                bvh,
                                r,
                                crate::trace::NodeTest::fastest(),
                                &mut Default::default(),
                            )
                        })
                        .count();
                    let g = to_byte(1.0 - occ as f32 / 4.0);
                    [g, g, g]
                }
            }
        })
        .collect();
    let mut rgb = vec![0u8; 3 * w as usize * h as usize];
    for (&(x, y), c) in order.iter().zip(&colours) {
        let o = 3 * (y as usize * w as usize + x as usize);
        rgb[o..o + 3].copy_from_slice(c);
    }
    Image {
        width: w,
        height: h,
        rgb,
    }
}

/// Errors of PNG input and output.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// File system error.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// Encoder error.
    #[error("PNG encoding failed: {0}")]
    Encode(#[from] png::EncodingError),
    /// Decoder error.
    #[error("PNG decoding failed: {0}")]
    Decode(#[from] png::DecodingError),
    /// The PNG is not 8-bit RGB.
    #[error("expected an 8-bit RGB PNG, found {0:?} {1:?}")]
    Format(png::ColorType, png::BitDepth),
}

impl Image {
    /// Write as an 8-bit RGB PNG.
    pub fn write_png<W: Write>(&self, out: W) -> Result<(), ImageError> {
        let mut enc = png::Encoder::new(BufWriter::new(out), self.width, self.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header()?;
        w.write_image_data(&self.rgb)?;
        w.finish()?;
        Ok(())
    }

    /// Read an 8-bit RGB PNG.
    pub fn read_png<R: Read>(input: R) -> Result<Image, ImageError> {
        let dec = png::Decoder::new(std::io::BufReader::new(input));
        let mut r = dec.read_info()?;
        let mut buf = vec![0u8; r.output_buffer_size()];
        let info = r.next_frame(&mut buf)?;
        if info.color_type != png::ColorType::Rgb || info.bit_depth != png::BitDepth::Eight {
            return Err(ImageError::Format(info.color_type, info.bit_depth));
        }
        buf.truncate(info.buffer_size());
        Ok(Image {
            width: info.width,
            height: info.height,
            rgb: buf,
        })
    }
}
