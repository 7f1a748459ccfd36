//! `--set field=value`: any field of the engine configuration, reachable without a flag of
//! its own. Shared by the trajectory commands and the Middlebury evaluation.

use anyhow::{bail, Context, Result};
use handflow_flow::EngineConfig;

/// Applies `field=value` overrides to a configuration through its serde form, so every
/// field is reachable without a flag of its own.
pub fn apply_overrides(config: EngineConfig, overrides: &[String]) -> Result<EngineConfig> {
    let mut config = config;
    for item in overrides {
        let Some((key, raw)) = item.split_once('=') else {
            bail!("override `{item}`: expected `field=value`");
        };
        let key = key.trim();
        if let Some(flag) = FLAG_FIELDS.iter().find_map(|(field, flag)| (*field == key).then_some(*flag)) {
            bail!("override `{item}`: `{key}` has its own option, use {flag}");
        }
        let mut value = serde_json::to_value(&config).context("engine configuration")?;
        let Some(map) = value.as_object_mut() else { bail!("engine configuration is not a table") };
        if !map.contains_key(key) {
            let known: Vec<&str> = map.keys().map(String::as_str).collect();
            bail!("override `{item}`: no engine field `{key}` (fields: {})", known.join(", "));
        }
        let parsed =
            serde_json::from_str(raw.trim()).unwrap_or_else(|_| serde_json::Value::String(raw.trim().to_string()));
        map.insert(key.to_string(), parsed);
        config = serde_json::from_value(value).with_context(|| format!("override `{item}`: bad value for `{key}`"))?;
    }
    Ok(config)
}

/// Engine fields that a command-line option or the layout sets: overriding them with
/// `--set` would run something other than what the report says.
const FLAG_FIELDS: [(&str, &str); 4] = [
    ("seed", "--seed"),
    ("variant", "--variant"),
    ("particles_per_ray", "--particles-per-ray"),
    ("temporal", "--layout (multiview is two-frame, fb forwards/backwards)"),
];
