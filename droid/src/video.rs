//! MP4 through ffmpeg (Debian's, with libx264): JPEG frames in, RGB frames out.
//!
//! Writing pipes the recorded JPEGs as they are (`image2pipe`, MJPEG) into one ffmpeg per
//! camera, which encodes H.264 (yuv420p, one output frame per input frame, the rig's rate);
//! nothing is decoded in this process. Reading asks ffprobe for the size and lets ffmpeg
//! decode to raw RGB24, one frame per `width * height * 3` bytes.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("{tool} not found ({source}): install it with scripts/setup.sh (Debian package ffmpeg)")]
    Missing { tool: &'static str, source: std::io::Error },
    #[error("{path}: ffmpeg failed: {message}")]
    Ffmpeg { path: PathBuf, message: String },
    #[error("{path}: {what}: {source}")]
    Io { path: PathBuf, what: &'static str, source: std::io::Error },
}

fn spawn(tool: &'static str, cmd: &mut Command) -> Result<Child, VideoError> {
    cmd.spawn().map_err(|source| VideoError::Missing { tool, source })
}

fn stderr_text(child: &mut Child) -> String {
    let mut s = String::new();
    if let Some(mut e) = child.stderr.take() {
        let _ = e.read_to_string(&mut s);
    }
    s.trim().to_owned()
}

/// An MP4 being written from JPEG frames.
#[derive(Debug)]
pub struct Mp4Writer {
    path: PathBuf,
    child: Child,
    stdin: Option<ChildStdin>,
    frames: u64,
}

impl Mp4Writer {
    /// Starts ffmpeg writing `path` at `fps` frames per second.
    pub fn create(path: &Path, fps: u32) -> Result<Mp4Writer, VideoError> {
        let child = spawn(
            "ffmpeg",
            Command::new("ffmpeg")
                .args(["-hide_banner", "-nostdin", "-loglevel", "error", "-y"])
                .args(["-f", "image2pipe", "-c:v", "mjpeg", "-framerate", &fps.to_string(), "-i", "-"])
                // Even sizes for yuv420p; every input frame becomes one output frame.
                .args(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-fps_mode", "passthrough"])
                .args(["-c:v", "libx264", "-preset", "veryfast", "-crf", "18", "-pix_fmt", "yuv420p"])
                .args(["-threads", "1", "-movflags", "+faststart"])
                .arg(path)
                .stdin(Stdio::piped())
                .stdout(Stdio::null())
                .stderr(Stdio::piped()),
        )?;
        let mut w = Mp4Writer { path: path.to_owned(), child, stdin: None, frames: 0 };
        w.stdin = w.child.stdin.take();
        Ok(w)
    }

    /// Appends one frame (a whole JPEG file).
    pub fn push_jpeg(&mut self, jpeg: &[u8]) -> Result<(), VideoError> {
        let stdin = self.stdin.as_mut().expect("open until finish");
        if let Err(e) = stdin.write_all(jpeg) {
            self.stdin = None;
            let _ = self.child.wait();
            let message = stderr_text(&mut self.child);
            return Err(VideoError::Ffmpeg {
                path: self.path.clone(),
                message: if message.is_empty() { e.to_string() } else { message },
            });
        }
        self.frames += 1;
        Ok(())
    }

    /// Frames pushed so far.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// Closes the input and waits for ffmpeg; returns the number of frames.
    pub fn finish(mut self) -> Result<u64, VideoError> {
        self.stdin = None;
        let status = self.child.wait().map_err(|source| VideoError::Io {
            path: self.path.clone(),
            what: "waiting for ffmpeg",
            source,
        })?;
        if !status.success() {
            let message = stderr_text(&mut self.child);
            return Err(VideoError::Ffmpeg { path: self.path.clone(), message: format!("{status}: {message}") });
        }
        Ok(self.frames)
    }
}

/// Width, height and the number of decoded frames of a video (ffprobe, counting frames).
pub fn probe(path: &Path, count_frames: bool) -> Result<(u32, u32, Option<u64>), VideoError> {
    let mut cmd = Command::new("ffprobe");
    cmd.args(["-v", "error", "-select_streams", "v:0"]);
    if count_frames {
        cmd.args(["-count_frames", "-show_entries", "stream=width,height,nb_read_frames"]);
    } else {
        cmd.args(["-show_entries", "stream=width,height"]);
    }
    let out = cmd
        .args(["-of", "csv=p=0"])
        .arg(path)
        .output()
        .map_err(|source| VideoError::Missing { tool: "ffprobe", source })?;
    let text = String::from_utf8_lossy(&out.stdout).trim().to_owned();
    let fail = |message: String| VideoError::Ffmpeg { path: path.to_owned(), message };
    if !out.status.success() || text.is_empty() {
        return Err(fail(format!("not a readable video: {}", String::from_utf8_lossy(&out.stderr).trim())));
    }
    let parts: Vec<&str> = text.lines().next().unwrap_or("").split(',').collect();
    let num = |i: usize| parts.get(i).and_then(|p| p.trim().parse::<u64>().ok());
    let (Some(w), Some(h)) = (num(0), num(1)) else {
        return Err(fail(format!("ffprobe gave no size: {text:?}")));
    };
    Ok((w as u32, h as u32, if count_frames { num(2) } else { None }))
}

/// An MP4 being decoded to RGB24 frames.
#[derive(Debug)]
pub struct Mp4Reader {
    path: PathBuf,
    child: Child,
    stdout: ChildStdout,
    pub width: u32,
    pub height: u32,
}

impl Mp4Reader {
    pub fn open(path: &Path) -> Result<Mp4Reader, VideoError> {
        Mp4Reader::open_range(path, None)
    }

    /// Decodes from `start` (seconds: the first frame whose time is at least `start` minus a
    /// quarter frame at `fps`) for at most `frames` frames: one episode of a video holding many
    /// (LeRobot's v3.0 files).
    pub fn open_at(path: &Path, start: f64, fps: f64, frames: usize) -> Result<Mp4Reader, VideoError> {
        Mp4Reader::open_range(path, Some(((start - 0.25 / fps).max(0.0), frames)))
    }

    fn open_range(path: &Path, range: Option<(f64, usize)>) -> Result<Mp4Reader, VideoError> {
        let (width, height, _) = probe(path, false)?;
        let mut cmd = Command::new("ffmpeg");
        cmd.args(["-hide_banner", "-nostdin", "-loglevel", "error"]);
        if let Some((start, _)) = range {
            // Before -i: an accurate seek (decoded from the keyframe before, frames before
            // `start` dropped).
            cmd.args(["-ss", &format!("{start:.6}")]);
        }
        cmd.arg("-i").arg(path);
        if let Some((_, frames)) = range {
            cmd.args(["-frames:v", &frames.to_string()]);
        }
        let mut child = spawn(
            "ffmpeg",
            cmd.args(["-f", "rawvideo", "-pix_fmt", "rgb24", "-fps_mode", "passthrough", "-"])
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped()),
        )?;
        let stdout = child.stdout.take().expect("piped");
        Ok(Mp4Reader { path: path.to_owned(), child, stdout, width, height })
    }

    /// The next frame's RGB24 pixels; `None` at the end of the video.
    pub fn next_frame(&mut self) -> Result<Option<Vec<u8>>, VideoError> {
        let mut buf = vec![0u8; self.width as usize * self.height as usize * 3];
        let mut got = 0;
        while got < buf.len() {
            match self.stdout.read(&mut buf[got..]) {
                Ok(0) => break,
                Ok(k) => got += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(source) => return Err(VideoError::Io { path: self.path.clone(), what: "reading frames", source }),
            }
        }
        if got == buf.len() {
            return Ok(Some(buf));
        }
        let status = self.child.wait().map_err(|source| VideoError::Io {
            path: self.path.clone(),
            what: "waiting for ffmpeg",
            source,
        })?;
        if !status.success() || got != 0 {
            let message = stderr_text(&mut self.child);
            return Err(VideoError::Ffmpeg {
                path: self.path.clone(),
                message: format!("{status}, a frame cut at {got} bytes: {message}"),
            });
        }
        Ok(None)
    }
}

impl Drop for Mp4Reader {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Mp4Writer {
    fn drop(&mut self) {
        if self.stdin.is_some() {
            self.stdin = None;
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn jpeg(w: u16, h: u16, shade: u8) -> Vec<u8> {
        let px: Vec<u8> = (0..w as usize * h as usize).flat_map(|i| [shade, (i % 251) as u8, 255 - shade]).collect();
        labrig_episode::jpeg::encode_rgb(&px, w, h, 90).unwrap()
    }

    #[test]
    fn frames_in_equal_frames_out() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.mp4");
        let mut w = Mp4Writer::create(&p, 20).unwrap();
        for i in 0..23 {
            w.push_jpeg(&jpeg(32, 24, i * 10)).unwrap();
        }
        assert_eq!(w.finish().unwrap(), 23);
        assert_eq!(probe(&p, true).unwrap(), (32, 24, Some(23)));
        let mut r = Mp4Reader::open(&p).unwrap();
        let mut n = 0;
        while let Some(f) = r.next_frame().unwrap() {
            assert_eq!(f.len(), 32 * 24 * 3);
            n += 1;
        }
        assert_eq!(n, 23);
    }

    #[test]
    fn a_bad_frame_names_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.mp4");
        let mut w = Mp4Writer::create(&p, 20).unwrap();
        let r = w.push_jpeg(b"this is no jpeg").and_then(|_| w.finish().map(|_| ()));
        let e = r.unwrap_err().to_string();
        assert!(e.contains("bad.mp4: ffmpeg failed"), "{e}");
        let e = probe(&dir.path().join("none.mp4"), false).unwrap_err().to_string();
        assert!(e.contains("none.mp4") && e.contains("not a readable video"), "{e}");
    }
}
