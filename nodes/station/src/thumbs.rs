//! Camera thumbnails from the iceoryx2 frames: a thread of its own subscribes to every camera
//! (one subscriber more; the cameras publish with safe overflow, so a slow station loses its
//! own oldest frames and never holds a camera, the loop or the recorder back), keeps the
//! newest frame, and a few times a second scales it down and encodes it as JPEG.

use labrig_msgs::Nanos;
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::std_msgs::Header;
use labrig_runtime::Shutdown;
use labrig_runtime::frames::{FrameEncoding, FrameHeader, FrameNode};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One camera's newest thumbnail.
#[derive(Debug, Clone)]
pub struct Thumb {
    pub jpeg: Arc<Vec<u8>>,
    /// The enlarged view's pixels (twice the width, RGB), from the same frame: encoded only when
    /// the page asks for it ([`Thumb::large_jpeg`]), not for every camera at every cycle.
    pub large: Arc<(usize, usize, Vec<u8>)>,
    pub capture_ns: i64,
    pub sequence: u64,
    pub made: Instant,
    /// Frames seen from the camera in the last second.
    pub fps: f64,
}

pub type Thumbs = Arc<Mutex<BTreeMap<String, Thumb>>>;

/// The Foxglove channel of a camera's thumbnails.
pub fn preview_topic(camera: &str) -> String {
    labrig_msgs::topics::camera_preview(camera)
}

/// An image scaled to `width` (nearest sample), as RGB; None for a frame it cannot read.
pub fn scaled_rgb(h: &FrameHeader, px: &[u8], width: u32) -> Option<(usize, usize, Vec<u8>)> {
    let enc = h.encoding()?;
    let (src_w, src_h, rgb_src, stride, bpp): (usize, usize, Vec<u8>, usize, usize) = match enc {
        FrameEncoding::Jpeg => {
            let img = labrig_episode::jpeg::decode_rgb(px).ok()?;
            (img.width, img.height, img.pixels, img.width * 3, 3)
        }
        _ => {
            let bpp = enc.bytes_per_pixel()?;
            let stride = if h.stride > 0 { h.stride as usize } else { h.width as usize * bpp };
            if px.len() < stride * h.height as usize {
                return None;
            }
            (h.width as usize, h.height as usize, Vec::new(), stride, bpp)
        }
    };
    if src_w == 0 || src_h == 0 {
        return None;
    }
    let src: &[u8] = if enc == FrameEncoding::Jpeg { &rgb_src } else { px };
    let w = (width as usize).min(src_w);
    let hgt = (src_h * w / src_w).max(1);
    let mut out = Vec::with_capacity(w * hgt * 3);
    for y in 0..hgt {
        let sy = y * src_h / hgt;
        for x in 0..w {
            let sx = x * src_w / w;
            let p = &src[sy * stride + sx * bpp..];
            match enc {
                FrameEncoding::Rgb8 | FrameEncoding::Jpeg => out.extend_from_slice(&p[..3]),
                FrameEncoding::Bgr8 => out.extend_from_slice(&[p[2], p[1], p[0]]),
                FrameEncoding::Mono8 => out.extend_from_slice(&[p[0]; 3]),
                // Depth (mm): 0..4 m as white..black, no reading black.
                FrameEncoding::Depth16 => {
                    let mm = u16::from_le_bytes([p[0], p[1]]) as u32;
                    let v = if mm == 0 { 0 } else { 255 - (mm.min(4000) * 255 / 4000) as u8 };
                    out.extend_from_slice(&[v; 3]);
                }
            }
        }
    }
    Some((w, hgt, out))
}

impl Thumb {
    /// The enlarged view as JPEG.
    pub fn large_jpeg(&self) -> Option<Vec<u8>> {
        let (w, h, rgb) = &*self.large;
        jpeg(*w, *h, rgb)
    }
}

fn jpeg(w: usize, h: usize, rgb: &[u8]) -> Option<Vec<u8>> {
    let mut buf = Vec::new();
    jpeg_encoder::Encoder::new(&mut buf, 75).encode(rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb).ok()?;
    Some(buf)
}

/// Starts the thumbnail thread; it ends with `shutdown`. A camera with no publisher yet is
/// retried (the station may start before the cameras).
pub fn spawn(
    namespace: Option<String>,
    cameras: Vec<String>,
    hz: f64,
    width: u32,
    hub: Arc<crate::foxglove::Hub>,
    shutdown: Shutdown,
) -> anyhow::Result<(Thumbs, std::thread::JoinHandle<()>)> {
    let thumbs: Thumbs = Arc::default();
    let out = thumbs.clone();
    let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel::<anyhow::Result<()>>(1);
    let handle = std::thread::Builder::new().name("thumbnails".into()).spawn(move || {
        let node = match &namespace {
            Some(ns) => FrameNode::new_in(ns),
            None => FrameNode::new(),
        };
        let node = match node {
            Ok(n) => {
                let _ = ready_tx.send(Ok(()));
                n
            }
            Err(e) => {
                let _ = ready_tx.send(Err(e.into()));
                return;
            }
        };
        let mut subs: Vec<(String, Option<labrig_runtime::frames::FrameSubscriber>)> =
            cameras.into_iter().map(|c| (c, None)).collect();
        let mut seen: BTreeMap<String, Vec<Instant>> = BTreeMap::new();
        let period = Duration::from_secs_f64(1.0 / hz);
        let mut retry_at = Instant::now();
        while !shutdown.is_triggered() {
            let started = Instant::now();
            if started >= retry_at {
                for (cam, sub) in subs.iter_mut().filter(|(_, s)| s.is_none()) {
                    match node.subscriber(cam) {
                        Ok(s) => *sub = Some(s),
                        Err(e) => tracing::debug!("camera {cam}: {e} (retrying)"),
                    }
                }
                retry_at = started + Duration::from_secs(1);
            }
            for (cam, sub) in &subs {
                let Some(sub) = sub else { continue };
                let mut newest = None;
                loop {
                    match sub.receive() {
                        Ok(Some(f)) => {
                            seen.entry(cam.clone()).or_default().push(Instant::now());
                            newest = Some(f);
                        }
                        Ok(None) => break,
                        Err(e) => {
                            tracing::warn!("camera {cam}: {e}");
                            break;
                        }
                    }
                }
                let Some(frame) = newest else { continue };
                let h = *frame.header();
                let made = scaled_rgb(&h, frame.pixels(), width * 2).and_then(|(w2, h2, rgb2)| {
                    // The thumbnail: every other pixel of the enlarged view.
                    let (w1, h1) = ((w2 / 2).max(1), (h2 / 2).max(1));
                    let mut rgb1 = Vec::with_capacity(w1 * h1 * 3);
                    for y in 0..h1 {
                        for x in 0..w1 {
                            let i = ((y * 2).min(h2 - 1) * w2 + (x * 2).min(w2 - 1)) * 3;
                            rgb1.extend_from_slice(&rgb2[i..i + 3]);
                        }
                    }
                    Some((jpeg(w1, h1, &rgb1)?, (w2, h2, rgb2)))
                });
                drop(frame);
                let Some((small, large)) = made else { continue };
                let times = seen.entry(cam.clone()).or_default();
                let now = Instant::now();
                times.retain(|t| now.duration_since(*t) < Duration::from_secs(1));
                let fps = times.len() as f64;
                // Foxglove's preview of the camera: the thumbnail as a CompressedImage.
                let image = CompressedImage {
                    header: Header { stamp: Nanos(h.capture_ns).into(), frame_id: format!("{cam}_optical") },
                    format: "jpeg".into(),
                    data: small.clone(),
                };
                if let Ok(cdr) = labrig_msgs::encode(&image) {
                    hub.publish(&preview_topic(cam), h.capture_ns.max(0) as u64, cdr.into());
                }
                out.lock().expect("thumbnails").insert(
                    cam.clone(),
                    Thumb {
                        jpeg: Arc::new(small),
                        large: Arc::new(large),
                        capture_ns: h.capture_ns,
                        sequence: h.sequence,
                        made: now,
                        fps,
                    },
                );
            }
            if let Some(rest) = period.checked_sub(started.elapsed()) {
                std::thread::sleep(rest);
            }
        }
    })?;
    ready_rx.recv().map_err(|_| anyhow::anyhow!("the thumbnail thread died at start"))??;
    Ok((thumbs, handle))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_of_each_encoding_scale_to_the_asked_width() {
        let mut h = FrameHeader::default();
        (h.width, h.height, h.stride, h.encoding) = (8, 4, 24, FrameEncoding::Bgr8 as u16);
        let px: Vec<u8> = (0..8 * 4).flat_map(|i| [i as u8, 100, 200]).collect();
        let (w, hh, rgb) = scaled_rgb(&h, &px, 4).unwrap();
        assert_eq!((w, hh, rgb.len()), (4, 2, 24));
        assert_eq!(&rgb[..3], &[200, 100, 0], "BGR becomes RGB");
        h.encoding = FrameEncoding::Mono8 as u16;
        h.stride = 8;
        let (_, _, rgb) = scaled_rgb(&h, &[7u8; 32], 8).unwrap();
        assert!(rgb.iter().all(|&v| v == 7));
        // A short buffer is refused, not read past.
        assert!(scaled_rgb(&h, &[0u8; 10], 8).is_none());
    }
}
