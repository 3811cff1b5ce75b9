//! The sans-serif TrueType font labrig's PNG plots write their text with (Debian's DejaVu,
//! installed by setup), read once per process.

const CANDIDATES: [&str; 2] =
    ["/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", "/usr/share/fonts/TTF/DejaVuSans.ttf"];

/// DejaVuSans.ttf's bytes, or why there are none (the same answer on every call).
pub fn dejavu_sans() -> Result<&'static [u8], String> {
    static FONT: std::sync::OnceLock<Result<&'static [u8], String>> = std::sync::OnceLock::new();
    FONT.get_or_init(|| {
        let path = CANDIDATES.iter().find(|p| std::path::Path::new(p).exists()).ok_or_else(|| {
            format!(
                "no DejaVuSans.ttf for the plot's text (looked in {CANDIDATES:?}; apt-get install fonts-dejavu-core)"
            )
        })?;
        let bytes = std::fs::read(path).map_err(|e| format!("{path}: {e}"))?;
        Ok(&*Box::leak(bytes.into_boxed_slice()))
    })
    .clone()
}
