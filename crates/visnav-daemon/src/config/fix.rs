//! The `[fix]` section of a configuration file: [`FixParams`] whose keys override the pipeline's
//! defaults at any depth (a partial `[fix.pose.ransac]` keeps every other default of the
//! pipeline, which serde's own defaults would reset to the resection module's). Unknown keys are
//! errors naming the key; the retired wall-clock budget is refused with the key that replaced it.

use serde::Deserialize;

use visnav_core::fix::FixParams;

/// Why a `[fix]` table could not be read.
#[derive(Debug, thiserror::Error)]
pub enum FixConfigError {
    /// A key that no longer exists, with what replaced it.
    #[error("{key}: {replacement}")]
    Retired {
        /// The key.
        key: &'static str,
        /// What replaced it.
        replacement: &'static str,
    },
    /// A key or value serde refused (the message names the key).
    #[error("{0}")]
    Value(String),
}

/// Keys that were replaced, with the message that says by what.
const RETIRED_KEYS: [(&str, &str); 1] = [(
    "reloc_budget_ms",
    "replaced by reloc_budget_mwork (a work budget in millions of units, default 60: one unit is \
     a pixel through SURF or 16 descriptor comparisons), so that results do not depend on the \
     machine's speed or load",
)];

/// Settings from a `[fix]` TOML table over the defaults.
pub fn fix_params_from_toml(user: toml::Value) -> Result<FixParams, FixConfigError> {
    for (key, replacement) in RETIRED_KEYS {
        if user.get(key).is_some() {
            return Err(FixConfigError::Retired { key, replacement });
        }
    }
    let mut base = toml::Value::try_from(FixParams::default())
        .map_err(|e| FixConfigError::Value(e.to_string()))?;
    merge_toml(&mut base, user);
    base.try_into::<FixParams>()
        .map_err(|e| FixConfigError::Value(e.to_string()))
}

/// Deep merge of `over` into `base` (tables merged key by key, other values replaced).
fn merge_toml(base: &mut toml::Value, over: toml::Value) {
    match (base, over) {
        (toml::Value::Table(b), toml::Value::Table(o)) => {
            for (k, v) in o {
                match b.get_mut(&k) {
                    Some(slot) => merge_toml(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, v) => *slot = v,
    }
}

/// `deserialize_with` helper for a `[fix]` section: [`fix_params_from_toml`].
pub fn deserialize_fix_params<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> Result<FixParams, D::Error> {
    let user = toml::Value::deserialize(d)?;
    fix_params_from_toml(user).map_err(serde::de::Error::custom)
}

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_core::fix::engine::default_pose_config;

    #[test]
    fn partial_toml_keeps_the_pipeline_defaults() {
        let v: toml::Value =
            toml::from_str("ratio = 0.9\n[pose.ransac]\nthreshold_px = 2.0\n").unwrap();
        let p = fix_params_from_toml(v).unwrap();
        assert_eq!(p.ratio, 0.9);
        assert_eq!(p.pose.ransac.threshold_px, 2.0);
        // Untouched nested defaults are the pipeline's, not the resection module's.
        assert_eq!(
            p.pose.refine.sigma_inflation,
            default_pose_config().refine.sigma_inflation
        );
        assert!(p.pose.refine.use_attitude_prior);
        let bad: toml::Value = toml::from_str("[pose.ransac]\nthreshhold_px = 2.0\n").unwrap();
        let e = fix_params_from_toml(bad).unwrap_err().to_string();
        assert!(e.contains("threshhold_px"), "{e}");
        // The old wall-clock budget is refused with the key that replaced it.
        let old: toml::Value = toml::from_str("reloc_budget_ms = 5000.0\n").unwrap();
        let e = fix_params_from_toml(old).unwrap_err().to_string();
        assert!(
            e.contains("reloc_budget_ms") && e.contains("reloc_budget_mwork"),
            "{e}"
        );
    }
}
