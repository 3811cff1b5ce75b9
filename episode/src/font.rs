//! The sans-serif TrueType font labrig's PNG plots write their text with (Debian's DejaVu,
//! installed by setup), read once per process.

use std::sync::Arc;

const CANDIDATES: [&str; 2] =
    ["/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", "/usr/share/fonts/TTF/DejaVuSans.ttf"];

/// Why there is no font (the same answer on every call of [`dejavu_sans`]).
#[derive(Debug, Clone, thiserror::Error)]
pub enum FontError {
    #[error("no DejaVuSans.ttf for the plot's text (looked in {looked_in:?}; apt-get install fonts-dejavu-core)")]
    NotFound { looked_in: &'static [&'static str] },
    #[error("{path}: {source}")]
    Read {
        path: &'static str,
        #[source]
        source: Arc<std::io::Error>,
    },
}

/// DejaVuSans.ttf's bytes, or why there are none (the same answer on every call).
pub fn dejavu_sans() -> Result<&'static [u8], FontError> {
    static FONT: std::sync::OnceLock<Result<&'static [u8], FontError>> = std::sync::OnceLock::new();
    FONT.get_or_init(|| {
        let path = CANDIDATES
            .iter()
            .find(|p| std::path::Path::new(p).exists())
            .ok_or(FontError::NotFound { looked_in: &CANDIDATES })?;
        let bytes = std::fs::read(path).map_err(|e| FontError::Read { path, source: Arc::new(e) })?;
        Ok(&*Box::leak(bytes.into_boxed_slice()))
    })
    .clone()
}
