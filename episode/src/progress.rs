//! The one progress-bar style of labrig's long-running tools (the demo, rollouts, benches,
//! calibration, dataset exports): `{spinner} <template>  {msg}  [{elapsed}]`, ticking on its
//! own so a slow step still shows the tool is alive, hidden when the tool prints JSON.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::time::Duration;

/// A bar over `len` steps; `template` is indicatif's (`{bar:25} {pos}/{len} episodes`). A
/// template is code, not input: a bad one panics.
pub fn bar(template: &str, len: u64, hidden: bool) -> ProgressBar {
    let bar = ProgressBar::new(len);
    let style = ProgressStyle::with_template(&format!("{{spinner}} {template}  {{msg}}  [{{elapsed}}]"))
        .unwrap_or_else(|e| panic!("progress template `{template}`: {e}"));
    bar.set_style(style);
    if hidden {
        bar.set_draw_target(ProgressDrawTarget::hidden());
    }
    bar.enable_steady_tick(Duration::from_millis(200));
    bar
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_hidden_bar_counts() {
        let b = super::bar("{bar:10} {pos}/{len}", 3, true);
        b.inc(2);
        assert_eq!(b.position(), 2);
        assert!(b.is_hidden());
    }
}
