//! Which convolutions a plan runs as Winograd's fast algorithm ([`crate::WinogradConv`]): a
//! precision its user chooses when compiling it (`prl compile --winograd`, recorded in
//! `plan.json`), and which the environment variable `PRL_WINOGRAD` overrides when loading it.

use serde::{Deserialize, Serialize};

/// Which stride-1 float convolutions run as [`crate::WinogradConv`] (those with 32 channels or
/// more on each side whose products come to at most 3/4 of the direct form's; the others stay
/// direct).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum Winograd {
    /// None: the direct form ([`crate::PackedConv`]) for every layer. The default, which keeps
    /// PRL-Track's boxes within 1e-4 px of the official tracker's on its reference traces.
    #[default]
    #[serde(rename = "off")]
    Off,
    /// The 3x3 ones, as F(2x2, 3x3).
    #[serde(rename = "3x3")]
    ThreeByThree,
    /// The 3x3 ones and the 5x5 ones (F(2x2, 5x5)).
    #[serde(rename = "all")]
    All,
}

impl Winograd {
    /// The names [`std::str::FromStr`] takes, as `prl compile --winograd` lists them.
    pub const NAMES: [&'static str; 3] = ["off", "3x3", "all"];

    /// Whether no convolution runs as Winograd's (for `skip_serializing_if`).
    pub fn is_off(&self) -> bool {
        *self == Winograd::Off
    }

    /// The kernel sides it runs as Winograd's.
    pub fn kernel_sides(self) -> &'static [usize] {
        match self {
            Winograd::Off => &[],
            Winograd::ThreeByThree => &[3],
            Winograd::All => &[3, 5],
        }
    }

    /// Its name: `off`, `3x3`, `all`.
    pub fn name(self) -> &'static str {
        match self {
            Winograd::Off => "off",
            Winograd::ThreeByThree => "3x3",
            Winograd::All => "all",
        }
    }

    /// The choice `PRL_WINOGRAD` makes over a plan's own, when it is set to one of
    /// [`Self::NAMES`] (read once; another value is ignored, and [`winograd_warning`] says so).
    pub fn from_env() -> Option<Winograd> {
        static CHOICE: std::sync::OnceLock<Option<Winograd>> = std::sync::OnceLock::new();
        *CHOICE.get_or_init(|| std::env::var("PRL_WINOGRAD").ok()?.parse().ok())
    }
}

impl std::str::FromStr for Winograd {
    type Err = String;

    fn from_str(s: &str) -> Result<Winograd, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "off" => Ok(Winograd::Off),
            "3x3" => Ok(Winograd::ThreeByThree),
            "all" => Ok(Winograd::All),
            other => Err(format!("`{other}` is not one of {}", Winograd::NAMES.join(", "))),
        }
    }
}

/// A message when `PRL_WINOGRAD` is set to a value the runtime does not know.
pub fn winograd_warning() -> Option<String> {
    let v = std::env::var("PRL_WINOGRAD").ok()?;
    let e = v.parse::<Winograd>().err()?;
    Some(format!("PRL_WINOGRAD={v}: {e}; the plan's own choice is used"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_and_serialise_alike() {
        for name in Winograd::NAMES {
            let w: Winograd = name.parse().unwrap();
            assert_eq!(w.name(), name);
            assert_eq!(serde_json::to_string(&w).unwrap(), format!("\"{name}\""));
            assert_eq!(serde_json::from_str::<Winograd>(&format!("\"{name}\"")).unwrap(), w);
        }
        assert_eq!(" ALL ".parse::<Winograd>(), Ok(Winograd::All));
        assert!("5x5".parse::<Winograd>().unwrap_err().contains("off, 3x3, all"));
        assert_eq!(Winograd::All.kernel_sides(), [3, 5]);
        assert!(Winograd::default().kernel_sides().is_empty());
    }
}
