//! `mc-gateway --check-config`: what resolving a configuration does not check by itself — the
//! files and certificates it names, and whether this build can run it — and the report of every
//! option with its value and where that value came from.

use std::path::Path;

use super::{options::DefaultText, specs, Config, Link, Origin};

/// What is wrong with `config` beyond its values, each naming the option and where it was given;
/// empty when the gateway can start with it.
pub fn problems(config: &Config) -> Vec<String> {
    let mut out = Vec::new();
    let mut problem = |key: &str, why: String| {
        out.push(match config.origins.of(key) {
            Origin::Default => format!("{} (default): {why}", flag(key)),
            origin => format!("{origin}: {why}"),
        });
    };
    match &config.can.link {
        #[cfg(feature = "demo")]
        Link::Simulated {
            island_file: Some(p),
        } => {
            if let Err(e) = crate::demo::load_island(Some(p)) {
                problem("island_file", e.to_string());
            }
        }
        #[cfg(not(feature = "demo"))]
        Link::Simulated { .. } => problem(
            "sim",
            "the simulated island needs the `demo` build feature".into(),
        ),
        _ => {}
    }
    #[cfg(not(feature = "demo"))]
    if let super::Broker::Embedded { .. } = config.mqtt.broker {
        problem(
            "broker",
            "no broker configured, and the embedded demo broker needs the `demo` build feature"
                .into(),
        );
    }
    // Reads and parses the CA file (or the system's roots), as the start does.
    if let Err(e) = crate::mqtt::options(&config.mqtt, &config.topics) {
        let key = if config.settings.tls_ca.is_some() {
            "tls_ca"
        } else {
            "tls"
        };
        problem(key, e.to_string());
    }
    if let Some(dir) = &config.settings.fw_dir {
        if !dir.is_dir() {
            problem("fw_dir", format!("{} is not a directory", dir.display()));
        }
    }
    if let Some(dir) = &config.log.dir {
        if let Some(why) = unusable_dir(dir) {
            problem("log_dir", why);
        }
    }
    #[cfg(not(feature = "web"))]
    if config.web.configured && config.web.listen.is_some() {
        problem(
            "http",
            "the island view (and /metrics) needs the `web` build feature".into(),
        );
    }
    out
}

/// Why `dir` cannot hold the log: a file where the directory should be, or no directory to create
/// it in.
fn unusable_dir(dir: &Path) -> Option<String> {
    if dir.exists() {
        return (!dir.is_dir()).then(|| format!("{} is not a directory", dir.display()));
    }
    // Created at start-up, with its parents: the nearest existing ancestor must be a directory.
    let existing = dir.ancestors().find(|a| a.exists())?;
    (!existing.is_dir()).then(|| {
        format!(
            "{} cannot be created: {} is not a directory",
            dir.display(),
            existing.display()
        )
    })
}

/// `--flag` of a TOML key.
fn flag(key: &str) -> String {
    format!("--{}", key.replace('_', "-"))
}

/// Every option that is set, with its value (secrets hidden): what the audit trail's `start`
/// record says the gateway ran with.
pub fn set_values(config: &Config) -> std::collections::BTreeMap<String, String> {
    let specs = specs();
    config
        .settings
        .shown()
        .into_iter()
        .filter_map(|(key, value)| {
            let secret = specs.iter().any(|s| s.key == key && s.secret);
            let value = value?;
            let value = if secret {
                "(set, hidden)".to_owned()
            } else {
                value
            };
            Some((key.to_owned(), value))
        })
        .collect()
}

/// Every option with its value and origin, then what the values resolve to.
pub fn report(config: &Config) -> String {
    let specs = specs();
    let rows: Vec<(String, String, String)> = config
        .settings
        .shown()
        .into_iter()
        .map(|(key, value)| {
            let spec = specs.iter().find(|s| s.key == key);
            let value = match (value, spec) {
                (Some(_), Some(s)) if s.secret => "(set, hidden)".to_owned(),
                (Some(v), _) => v,
                (None, Some(s)) if matches!(s.default, DefaultText::None) => "unset".to_owned(),
                (None, Some(s)) => format!("unset ({})", s.default.render().replace('`', "")),
                (None, None) => "unset".to_owned(),
            };
            let origin = match config.origins.of(key) {
                Origin::Default => "default".to_owned(),
                o => o.to_string(),
            };
            (flag(key), value, origin)
        })
        .collect();
    let w0 = rows.iter().map(|r| r.0.len()).max().unwrap_or(0);
    let w1 = rows
        .iter()
        .map(|r| r.1.chars().count())
        .max()
        .unwrap_or(0)
        .min(48);
    let mut out = format!("{:w0$}  {:w1$}  from\n", "option", "value");
    for (f, v, o) in rows {
        out.push_str(&format!("{f:w0$}  {v:w1$}  {o}\n"));
    }
    out.push_str(&format!(
        "\nresolved: broker {}; CAN {}; MQTT client id {}; commands on {}, events on {}; \
         island view {}; log {}\n",
        config.mqtt.broker,
        config.can.link,
        config.mqtt.client_id,
        config.topics.commands,
        config.topics.events,
        config.web.listen.map_or_else(
            || "off".to_owned(),
            |a| format!("on {a} (/metrics, /healthz, /readyz)")
        ),
        config.log.dir.as_ref().map_or_else(
            || "to stderr only".to_owned(),
            |d| format!("in {}", d.display())
        ),
    ));
    for w in &config.warnings {
        out.push_str(&format!("note: {w}\n"));
    }
    out
}
