//! Camera frames on shared memory (iceoryx2): five camera streams do not fit DDS.
//!
//! One publish-subscribe service per camera, `labrig/camera/<id>/frames`, payload `[u8]`
//! (the pixels) with a [`FrameHeader`] user header. Subscribers borrow the publisher's memory:
//! no copy between processes. Type names are set explicitly so that other languages (the PyPI
//! `iceoryx2` package) and other builds can open the same service.

#![allow(unsafe_code)] // Only the ZeroCopySend derive below expands to an `unsafe impl`.

use iceoryx2::prelude::*;
use iceoryx2::service::ipc_threadsafe;
use labrig_msgs::Nanos;

type Ipc = ipc_threadsafe::Service;

/// Longest camera id a header can carry (bytes of UTF-8).
pub const CAMERA_ID_LEN: usize = 32;

/// Version of the frame header layout; bump on any change.
pub const FRAME_HEADER_VERSION: u16 = 1;

/// Pixel layout of a frame's payload.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u16)]
pub enum FrameEncoding {
    Rgb8 = 1,
    Bgr8 = 2,
    Mono8 = 3,
    /// 16-bit depth in millimetres, little endian.
    Depth16 = 4,
    Jpeg = 5,
}

impl FrameEncoding {
    pub fn from_u16(v: u16) -> Option<FrameEncoding> {
        Some(match v {
            1 => Self::Rgb8,
            2 => Self::Bgr8,
            3 => Self::Mono8,
            4 => Self::Depth16,
            5 => Self::Jpeg,
            _ => return None,
        })
    }

    /// Bytes per pixel for raw encodings; `None` for compressed ones.
    pub fn bytes_per_pixel(self) -> Option<usize> {
        match self {
            Self::Rgb8 | Self::Bgr8 => Some(3),
            Self::Mono8 => Some(1),
            Self::Depth16 => Some(2),
            Self::Jpeg => None,
        }
    }

    /// The sensor_msgs/Image encoding string.
    pub fn ros_name(self) -> &'static str {
        match self {
            Self::Rgb8 => "rgb8",
            Self::Bgr8 => "bgr8",
            Self::Mono8 => "mono8",
            Self::Depth16 => "16UC1",
            Self::Jpeg => "jpeg",
        }
    }
}

/// Per-frame metadata travelling beside the pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
#[type_name("labrig::FrameHeader")]
pub struct FrameHeader {
    pub version: u16,
    /// A [`FrameEncoding`] value.
    pub encoding: u16,
    pub width: u32,
    pub height: u32,
    /// Bytes per row.
    pub stride: u32,
    camera_id: [u8; CAMERA_ID_LEN],
    /// Per-camera frame counter; gaps mean dropped frames.
    pub sequence: u64,
    /// Hardware capture time, ns (the arrival time where a camera has none).
    pub capture_ns: i64,
    /// When the frame reached the camera node, ns.
    pub arrival_ns: i64,
    /// Wall time when it was handed to shared memory (after the copy, just before send), ns:
    /// subscribers subtract it from their receive time for transport latency.
    pub publish_ns: i64,
}

impl Default for FrameHeader {
    fn default() -> Self {
        FrameHeader {
            version: FRAME_HEADER_VERSION,
            encoding: FrameEncoding::Rgb8 as u16,
            width: 0,
            height: 0,
            stride: 0,
            camera_id: [0; CAMERA_ID_LEN],
            sequence: 0,
            capture_ns: 0,
            arrival_ns: 0,
            publish_ns: 0,
        }
    }
}

impl FrameHeader {
    pub fn camera_id(&self) -> &str {
        let end = self.camera_id.iter().position(|&b| b == 0).unwrap_or(CAMERA_ID_LEN);
        std::str::from_utf8(&self.camera_id[..end]).unwrap_or("<invalid utf-8>")
    }

    pub fn encoding(&self) -> Option<FrameEncoding> {
        FrameEncoding::from_u16(self.encoding)
    }
}

/// Description of the frames one camera publishes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameFormat {
    pub encoding: FrameEncoding,
    pub width: u32,
    pub height: u32,
}

impl FrameFormat {
    /// Payload size of one raw frame (for compressed encodings: the bound to reserve).
    pub fn frame_bytes(&self) -> usize {
        self.width as usize * self.height as usize * self.encoding.bytes_per_pixel().unwrap_or(3)
    }
}

#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    #[error("camera id {0:?} is empty, longer than {CAMERA_ID_LEN} bytes or not [A-Za-z0-9_-]")]
    BadCameraId(String),
    #[error("camera {camera}: {what}: {message}")]
    Shm { camera: String, what: &'static str, message: String },
    #[error("camera {camera}: frame of {got} bytes does not match {width}x{height} {encoding:?} ({expected} bytes)")]
    SizeMismatch { camera: String, got: usize, expected: usize, width: u32, height: u32, encoding: FrameEncoding },
    #[error("camera {camera}: frame header version {found} is not supported (this build reads {FRAME_HEADER_VERSION})")]
    Version { camera: String, found: u16 },
}

/// Environment variable that puts every frame channel of a process under its own namespace
/// (`labrig/<ns>/camera/<id>/frames`), so two rigs (or two tests) on one machine stay apart,
/// as ROS_DOMAIN_ID does for DDS.
pub const NAMESPACE_ENV: &str = "LABRIG_FRAMES_NAMESPACE";

/// The frame namespace this process uses by default ([`NAMESPACE_ENV`], empty = none).
pub fn default_namespace() -> Option<String> {
    std::env::var(NAMESPACE_ENV).ok().filter(|ns| !ns.is_empty())
}

/// The iceoryx2 service name of a camera's frames in `namespace`.
pub fn service_name_in(namespace: Option<&str>, camera_id: &str) -> String {
    labrig_msgs::topics::frame_service(namespace, camera_id)
}

/// The iceoryx2 service name of a camera's frames (in this process's default namespace).
pub fn service_name(camera_id: &str) -> String {
    service_name_in(default_namespace().as_deref(), camera_id)
}

fn check_camera_id(id: &str) -> Result<[u8; CAMERA_ID_LEN], FrameError> {
    let ok = !id.is_empty()
        && id.len() <= CAMERA_ID_LEN
        && id.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
    if !ok {
        return Err(FrameError::BadCameraId(id.to_owned()));
    }
    let mut out = [0u8; CAMERA_ID_LEN];
    out[..id.len()].copy_from_slice(id.as_bytes());
    Ok(out)
}

/// An iceoryx2 node for frame channels. iceoryx2's own signal handling is off: the labrig
/// runtime handles SIGINT/SIGTERM ([`crate::lifecycle`]).
pub struct FrameNode {
    node: Node<Ipc>,
    namespace: Option<String>,
}

impl std::fmt::Debug for FrameNode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FrameNode")
    }
}

/// How many frames a subscriber may queue before the oldest is overwritten.
pub const SUBSCRIBER_BUFFER: usize = 4;

impl FrameNode {
    /// A node in the default namespace ([`NAMESPACE_ENV`]).
    pub fn new() -> Result<FrameNode, FrameError> {
        FrameNode::with_namespace(default_namespace())
    }

    /// A node whose channels live under `namespace`.
    pub fn new_in(namespace: &str) -> Result<FrameNode, FrameError> {
        FrameNode::with_namespace(Some(namespace.to_owned()).filter(|ns| !ns.is_empty()))
    }

    fn with_namespace(namespace: Option<String>) -> Result<FrameNode, FrameError> {
        // iceoryx2 logs to stderr on its own; its warning about running without a config
        // file is expected (labrig configures services in code).
        iceoryx2::prelude::set_log_level(LogLevel::Error);
        let node = NodeBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Ipc>()
            .map_err(|e| FrameError::Shm { camera: String::new(), what: "create node", message: format!("{e:?}") })?;
        Ok(FrameNode { node, namespace })
    }

    fn service(
        &self,
        camera_id: &str,
    ) -> Result<iceoryx2::service::port_factory::publish_subscribe::PortFactory<Ipc, [u8], FrameHeader>, FrameError>
    {
        let shm = |what, e: String| FrameError::Shm { camera: camera_id.to_owned(), what, message: e };
        let name: ServiceName = service_name_in(self.namespace.as_deref(), camera_id)
            .as_str()
            .try_into()
            .map_err(|e| shm("service name", format!("{e:?}")))?;
        self.node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .user_header::<FrameHeader>()
            // A slow subscriber loses the oldest frames, never stalls the camera.
            .enable_safe_overflow(true)
            .subscriber_max_buffer_size(SUBSCRIBER_BUFFER)
            .subscriber_max_borrowed_samples(SUBSCRIBER_BUFFER)
            .history_size(1)
            .max_subscribers(16)
            .max_publishers(1)
            .open_or_create()
            .map_err(|e| shm("open service", format!("{e:?}")))
    }

    /// The publisher of one camera's frames.
    pub fn publisher(&self, camera_id: &str, format: FrameFormat) -> Result<FramePublisher, FrameError> {
        let id = check_camera_id(camera_id)?;
        let service = self.service(camera_id)?;
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(format.frame_bytes())
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(2)
            .create()
            .map_err(|e| FrameError::Shm {
                camera: camera_id.to_owned(),
                what: "create publisher",
                message: format!("{e:?}"),
            })?;
        Ok(FramePublisher { publisher, camera: camera_id.to_owned(), id, format, sequence: 0 })
    }

    /// A subscriber to one camera's frames.
    pub fn subscriber(&self, camera_id: &str) -> Result<FrameSubscriber, FrameError> {
        check_camera_id(camera_id)?;
        let service = self.service(camera_id)?;
        let subscriber = service.subscriber_builder().buffer_size(SUBSCRIBER_BUFFER).create().map_err(|e| {
            FrameError::Shm { camera: camera_id.to_owned(), what: "create subscriber", message: format!("{e:?}") }
        })?;
        Ok(FrameSubscriber { subscriber, camera: camera_id.to_owned() })
    }
}

/// Publishes one camera's frames.
pub struct FramePublisher {
    publisher: iceoryx2::port::publisher::Publisher<Ipc, [u8], FrameHeader>,
    camera: String,
    id: [u8; CAMERA_ID_LEN],
    format: FrameFormat,
    sequence: u64,
}

impl std::fmt::Debug for FramePublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "FramePublisher({})", self.camera)
    }
}

impl FramePublisher {
    /// What this publisher sends.
    pub fn format(&self) -> &FrameFormat {
        &self.format
    }

    /// Copies `pixels` into shared memory once and publishes it with a header; returns the
    /// frame's sequence number. Raw encodings must match the format's size exactly.
    pub fn publish(&mut self, pixels: &[u8], capture: Nanos, arrival: Nanos) -> Result<u64, FrameError> {
        let f = &self.format;
        if f.encoding.bytes_per_pixel().is_some() && pixels.len() != f.frame_bytes() {
            return Err(FrameError::SizeMismatch {
                camera: self.camera.clone(),
                got: pixels.len(),
                expected: f.frame_bytes(),
                width: f.width,
                height: f.height,
                encoding: f.encoding,
            });
        }
        let shm = |what, e: String| FrameError::Shm { camera: self.camera.clone(), what, message: e };
        let mut sample = self.publisher.loan_slice_uninit(pixels.len()).map_err(|e| shm("loan", format!("{e:?}")))?;
        let seq = self.sequence;
        *sample.user_header_mut() = FrameHeader {
            version: FRAME_HEADER_VERSION,
            encoding: f.encoding as u16,
            width: f.width,
            height: f.height,
            stride: f.width * f.encoding.bytes_per_pixel().unwrap_or(0) as u32,
            camera_id: self.id,
            sequence: seq,
            capture_ns: capture.0,
            arrival_ns: arrival.0,
            publish_ns: 0,
        };
        let mut sample = sample.write_from_slice(pixels);
        sample.user_header_mut().publish_ns = crate::Clock::Wall.now().0;
        sample.send().map_err(|e| shm("send", format!("{e:?}")))?;
        self.sequence += 1;
        Ok(seq)
    }
}

/// Receives one camera's frames.
pub struct FrameSubscriber {
    subscriber: iceoryx2::port::subscriber::Subscriber<Ipc, [u8], FrameHeader>,
    camera: String,
}

impl std::fmt::Debug for FrameSubscriber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "FrameSubscriber({})", self.camera)
    }
}

/// A received frame, borrowed from shared memory until dropped.
pub struct Frame {
    sample: iceoryx2::sample::Sample<Ipc, [u8], FrameHeader>,
}

impl std::fmt::Debug for Frame {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Frame").field("header", self.header()).field("bytes", &self.pixels().len()).finish()
    }
}

impl Frame {
    pub fn header(&self) -> &FrameHeader {
        self.sample.user_header()
    }
    pub fn pixels(&self) -> &[u8] {
        self.sample.payload()
    }
}

impl FrameSubscriber {
    /// The next waiting frame, if any. Frames with an unknown header version are refused.
    pub fn receive(&self) -> Result<Option<Frame>, FrameError> {
        let sample = self.subscriber.receive().map_err(|e| FrameError::Shm {
            camera: self.camera.clone(),
            what: "receive",
            message: format!("{e:?}"),
        })?;
        match sample {
            None => Ok(None),
            Some(sample) => {
                let found = sample.user_header().version;
                if found != FRAME_HEADER_VERSION {
                    return Err(FrameError::Version { camera: self.camera.clone(), found });
                }
                Ok(Some(Frame { sample }))
            }
        }
    }
}

/// A frame copied out of shared memory: it holds no sample of the publisher's.
#[derive(Clone)]
pub struct OwnedFrame {
    header: FrameHeader,
    pixels: Vec<u8>,
}

impl std::fmt::Debug for OwnedFrame {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OwnedFrame").field("header", &self.header).field("bytes", &self.pixels.len()).finish()
    }
}

impl OwnedFrame {
    pub fn new(header: FrameHeader, pixels: Vec<u8>) -> OwnedFrame {
        OwnedFrame { header, pixels }
    }
    pub fn header(&self) -> &FrameHeader {
        &self.header
    }
    pub fn pixels(&self) -> &[u8] {
        &self.pixels
    }
}

impl From<&Frame> for OwnedFrame {
    fn from(f: &Frame) -> OwnedFrame {
        OwnedFrame { header: *f.header(), pixels: f.pixels().to_vec() }
    }
}

/// Per camera, the frames taken and not yet handed on, and how many were let go.
#[derive(Default)]
struct IntakeQueues {
    frames: Vec<std::collections::VecDeque<OwnedFrame>>,
    /// Pixel bytes queued.
    bytes: Vec<usize>,
    dropped: Vec<u64>,
}

/// Frames taken from shared memory as they arrive by a thread of its own, and queued (copied)
/// until the owner takes them. A subscriber queues only [`SUBSCRIBER_BUFFER`] frames before a
/// camera overwrites the oldest, which is 200 ms at 20 Hz: a consumer that stalls longer (a
/// chunk's fsync on a busy disk, a burst of JPEG encoding) would lose frames. Behind the
/// intake it may stall for `per_camera` frames (and `per_camera_bytes`); past that the oldest
/// queued frame is let go and counted ([`FrameIntake::dropped`]). The cost: every frame is
/// copied once (five 1280x720 RGB cameras at 20 Hz: 276 MB/s of memcpy).
pub struct FrameIntake {
    cameras: Vec<String>,
    queues: std::sync::Arc<std::sync::Mutex<IntakeQueues>>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for FrameIntake {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameIntake").field("cameras", &self.cameras).finish_non_exhaustive()
    }
}

impl FrameIntake {
    /// Takes over `subscribers` (camera id, subscriber) on a thread named `name`, keeping at
    /// most `per_camera` frames and `per_camera_bytes` of pixels queued per camera (at least
    /// the newest frame).
    pub fn start(
        name: &str,
        subscribers: Vec<(String, FrameSubscriber)>,
        per_camera: usize,
        per_camera_bytes: usize,
    ) -> std::io::Result<FrameIntake> {
        use std::sync::atomic::Ordering;
        let cameras: Vec<String> = subscribers.iter().map(|(c, _)| c.clone()).collect();
        let queues = std::sync::Arc::new(std::sync::Mutex::new(IntakeQueues {
            frames: vec![Default::default(); cameras.len()],
            bytes: vec![0; cameras.len()],
            dropped: vec![0; cameras.len()],
        }));
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (q, halt) = (queues.clone(), stop.clone());
        let per_camera = per_camera.max(1);
        let thread = std::thread::Builder::new().name(name.to_owned()).spawn(move || {
            let mut taken: Vec<OwnedFrame> = Vec::new();
            // A receive error (a frame of a header version this build cannot read) is logged
            // once per camera until that camera's frames are readable again.
            let mut failing = vec![false; subscribers.len()];
            while !halt.load(Ordering::Relaxed) {
                for (i, (camera, sub)) in subscribers.iter().enumerate() {
                    loop {
                        match sub.receive() {
                            Ok(Some(f)) => {
                                taken.push(OwnedFrame::from(&f));
                                failing[i] = false;
                            }
                            Ok(None) => break,
                            Err(e) => {
                                if !std::mem::replace(&mut failing[i], true) {
                                    tracing::warn!("camera {camera}: {e}");
                                }
                                break;
                            }
                        }
                    }
                    if taken.is_empty() {
                        continue;
                    }
                    let mut g = q.lock().unwrap_or_else(|p| p.into_inner());
                    let IntakeQueues { frames, bytes, dropped } = &mut *g;
                    for f in taken.drain(..) {
                        bytes[i] += f.pixels.len();
                        frames[i].push_back(f);
                        while frames[i].len() > per_camera || (bytes[i] > per_camera_bytes && frames[i].len() > 1) {
                            if let Some(old) = frames[i].pop_front() {
                                bytes[i] -= old.pixels.len();
                                dropped[i] += 1;
                            }
                        }
                    }
                }
                // A subscriber holds 200 ms of frames at 20 Hz: every 5 ms is far inside that,
                // and costs under 1% of a core (every millisecond cost ~3% idle, debug build).
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
        })?;
        Ok(FrameIntake { cameras, queues, stop, thread: Some(thread) })
    }

    /// The camera ids, in the order given.
    pub fn cameras(&self) -> &[String] {
        &self.cameras
    }

    /// Every frame queued, per camera (in the order of [`FrameIntake::cameras`]), oldest first.
    pub fn take(&self) -> Vec<std::collections::VecDeque<OwnedFrame>> {
        let mut g = self.queues.lock().unwrap_or_else(|p| p.into_inner());
        g.bytes.iter_mut().for_each(|b| *b = 0);
        g.frames.iter_mut().map(std::mem::take).collect()
    }

    /// Frames queued now, per camera.
    pub fn queued(&self) -> Vec<usize> {
        self.queues.lock().unwrap_or_else(|p| p.into_inner()).frames.iter().map(|q| q.len()).collect()
    }

    /// Whether the intake thread still runs (it ends only when dropped, or if it panicked).
    pub fn running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Frames let go per camera because `per_camera` were queued already.
    pub fn dropped(&self) -> Vec<u64> {
        self.queues.lock().unwrap_or_else(|p| p.into_inner()).dropped.clone()
    }
}

impl Drop for FrameIntake {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_cross_shared_memory_with_their_header() {
        let node = FrameNode::new().unwrap();
        let cam = format!("unit{}", std::process::id());
        let fmt = FrameFormat { encoding: FrameEncoding::Rgb8, width: 4, height: 2 };
        let mut publisher = node.publisher(&cam, fmt.clone()).unwrap();
        let subscriber = node.subscriber(&cam).unwrap();
        let pixels: Vec<u8> = (0..24).collect();
        for i in 0..3 {
            assert_eq!(publisher.publish(&pixels, Nanos(10 + i), Nanos(20 + i)).unwrap(), i as u64);
        }
        for i in 0..3 {
            let frame = subscriber.receive().unwrap().expect("frame");
            let h = frame.header();
            assert_eq!(
                (h.camera_id(), h.sequence, h.capture_ns, h.width, h.height),
                (cam.as_str(), i, 10 + i as i64, 4, 2)
            );
            assert_eq!(h.encoding(), Some(FrameEncoding::Rgb8));
            assert_eq!(frame.pixels(), &pixels[..]);
        }
        assert!(subscriber.receive().unwrap().is_none());
        let err = publisher.publish(&pixels[..5], Nanos(0), Nanos(0)).unwrap_err();
        assert!(err.to_string().contains("does not match 4x2"), "{err}");
    }

    #[test]
    fn the_intake_queues_what_a_stalled_owner_has_not_taken_and_counts_what_it_lets_go() {
        let node = FrameNode::new().unwrap();
        let cam = format!("intake{}", std::process::id());
        let fmt = FrameFormat { encoding: FrameEncoding::Mono8, width: 2, height: 1 };
        let mut publisher = node.publisher(&cam, fmt).unwrap();
        let sub = |c: &str| vec![(c.to_owned(), node.subscriber(c).unwrap())];
        // Each frame is published once the intake holds (or has let go) the ones before it.
        let settled = |intake: &FrameIntake, published: u64| {
            let t0 = std::time::Instant::now();
            while intake.queued()[0] as u64 + intake.dropped()[0] < published {
                assert!(t0.elapsed() < std::time::Duration::from_secs(10), "the intake took nothing in 10 s");
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
        };
        let intake = FrameIntake::start("intake-test", sub(&cam), 10, 1 << 20).unwrap();
        assert!(intake.running());
        // Three times the subscriber's own buffer, published while the owner takes nothing.
        let n = 3 * SUBSCRIBER_BUFFER as u64;
        for i in 0..n {
            publisher.publish(&[i as u8, 0], Nanos(i as i64), Nanos(i as i64)).unwrap();
            settled(&intake, i + 1);
        }
        let got = intake.take();
        let seq: Vec<u64> = got[0].iter().map(|f| f.header().sequence).collect();
        // The last 10 in order (the intake keeps 10); the two before them let go and counted.
        assert_eq!(seq, (n - 10..n).collect::<Vec<_>>());
        assert_eq!(got[0].back().unwrap().pixels(), &[(n - 1) as u8, 0]);
        assert_eq!(intake.dropped(), vec![2]);
        assert!(intake.take()[0].is_empty());
        drop(intake);

        // A byte budget of 5 frames' pixels keeps the newest 5 of 8.
        let cam2 = format!("intakeb{}", std::process::id());
        let fmt = FrameFormat { encoding: FrameEncoding::Mono8, width: 4, height: 1 };
        let mut publisher = node.publisher(&cam2, fmt).unwrap();
        let intake = FrameIntake::start("intake-test", sub(&cam2), 100, 20).unwrap();
        for i in 0..8u64 {
            publisher.publish(&[i as u8; 4], Nanos(i as i64), Nanos(i as i64)).unwrap();
            settled(&intake, i + 1);
        }
        let seq: Vec<u64> = intake.take()[0].iter().map(|f| f.header().sequence).collect();
        assert_eq!((seq, intake.dropped()[0]), ((3..8).collect::<Vec<_>>(), 3));
    }

    #[test]
    fn bad_camera_ids_are_refused() {
        let node = FrameNode::new().unwrap();
        for id in ["", "has space", &"x".repeat(40)] {
            assert!(matches!(node.subscriber(id), Err(FrameError::BadCameraId(_))));
        }
    }
}
