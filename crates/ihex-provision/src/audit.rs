//! `ihex-provision audit …`: read the gateway's audit trail (`docs/audit.md`) — `verify` checks the
//! hash chain and names the first broken line with what is wrong; `show` lists records for a
//! person, by element and time.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use ihex_audit::dir::{chain_files, file_lines, verify_dir};
use ihex_audit::verify::describe_head;
use ihex_audit::{Entry, Head};

/// The `audit` verbs.
#[derive(Subcommand)]
pub enum AuditCmd {
    /// Check the hash chain of an audit directory: exit 0 when it is whole, 1 with the first broken
    /// line and what is wrong with it.
    Verify(VerifyArgs),
    /// List audit records, oldest first: who (vouched user, claimed name), through which
    /// interface, what, and with what outcome.
    Show(ShowArgs),
}

#[derive(Args)]
pub struct VerifyArgs {
    /// The audit directory (the gateway's `--audit-dir`).
    dir: PathBuf,
    /// The chain's head as an anchor published it (`SEQ:SHA256`, the retained message on
    /// `<island>/ihex/audit/head`): the chain must reach it unchanged. Catches what the chain alone
    /// cannot: records cut off its end, an edit of its last line, a rewrite of the whole chain
    /// before the anchor was taken.
    #[arg(long)]
    head: Option<String>,
}

#[derive(Args)]
pub struct ShowArgs {
    /// The audit directory (the gateway's `--audit-dir`).
    dir: PathBuf,
    /// Only records about this element (node ID in hex, as the MQTT API writes it), and those
    /// about the whole island.
    #[arg(long)]
    element: Option<String>,
    /// Only records from this time on: RFC 3339 (`2026-11-25T14:00:00Z`), a date (`2026-11-25`,
    /// UTC), or an age such as `30m`, `2h`, `1d`.
    #[arg(long)]
    since: Option<String>,
    /// Only the records of this user (vouched or claimed).
    #[arg(long)]
    user: Option<String>,
    /// The records as the JSON lines they are (without the chain's `prev`).
    #[arg(long)]
    json: bool,
}

/// Runs a verb; `Ok(false)` for a broken chain.
pub fn run(cmd: AuditCmd) -> Result<bool> {
    match cmd {
        AuditCmd::Verify(a) => verify(&a),
        AuditCmd::Show(a) => show(&a).map(|()| true),
    }
}

fn verify(a: &VerifyArgs) -> Result<bool> {
    let anchor = match &a.head {
        Some(text) => Some(
            Head::from_text(text)
                .with_context(|| format!("--head {text:?}: expected SEQ:SHA256 (64 hex digits)"))?,
        ),
        None => None,
    };
    let files = chain_files(&a.dir)?;
    if files.is_empty() {
        anyhow::bail!("{}: no audit files (audit-*.jsonl)", a.dir.display());
    }
    let report = verify_dir(&a.dir, anchor)?;
    for loc in &report.recovered {
        say!("{loc}: torn line (a crash mid-write); the chain goes on after it in the next file");
    }
    match &report.broken {
        None => {
            say!(
                "ok: {} records in {} files, chained from the first to {}{}",
                report.records,
                files.len(),
                describe_head(report.head),
                if anchor.is_some() {
                    ", which the anchor confirms"
                } else {
                    ""
                }
            );
            Ok(true)
        }
        Some(finding) => {
            say!("BROKEN at {finding}");
            say!(
                "the {} records before it are chained (up to {})",
                report.records,
                describe_head(report.head)
            );
            Ok(false)
        }
    }
}

/// `--since` as RFC 3339 UTC text (comparable with the records' `ts` as text).
fn since_text(since: &str, now: time::OffsetDateTime) -> Result<String> {
    use time::format_description::well_known::Rfc3339;
    let s = since.trim();
    if let Ok(t) = time::OffsetDateTime::parse(s, &Rfc3339) {
        return Ok(ihex_audit::chain::rfc3339(t.into()));
    }
    if s.len() == 10 && s.as_bytes()[4] == b'-' {
        let t = time::OffsetDateTime::parse(&format!("{s}T00:00:00Z"), &Rfc3339)
            .with_context(|| format!("--since {s:?}: not a date"))?;
        return Ok(ihex_audit::chain::rfc3339(t.into()));
    }
    let (n, unit) = s.split_at(s.len().saturating_sub(1));
    let n: i64 = n.parse().with_context(|| {
        format!("--since {s:?}: expected RFC 3339, YYYY-MM-DD or an age like 30m, 2h, 1d")
    })?;
    let secs = match unit {
        "s" => n,
        "m" => n * 60,
        "h" => n * 3600,
        "d" => n * 86_400,
        _ => anyhow::bail!("--since {s:?}: an age ends in s, m, h or d"),
    };
    let t = now - time::Duration::seconds(secs);
    Ok(ihex_audit::chain::rfc3339(t.into()))
}

fn show(a: &ShowArgs) -> Result<()> {
    let since = a
        .since
        .as_deref()
        .map(|s| since_text(s, time::OffsetDateTime::now_utc()))
        .transpose()?;
    for path in chain_files(&a.dir)? {
        show_file(&path, a, since.as_deref())?;
    }
    Ok(())
}

fn show_file(path: &Path, a: &ShowArgs, since: Option<&str>) -> Result<()> {
    for line in file_lines(path)? {
        let Ok(entry) = serde_json::from_slice::<Entry>(&line.bytes) else {
            say!("{}: not a record (run `audit verify`)", line.loc);
            continue;
        };
        let r = &entry.record;
        if since.is_some_and(|s| entry.ts.as_str() < s) {
            continue;
        }
        if a.element.as_deref().is_some_and(|e| !r.concerns(e)) {
            continue;
        }
        if let Some(u) = &a.user {
            if r.user.as_deref() != Some(u.as_str()) && r.claimed.as_deref() != Some(u.as_str()) {
                continue;
            }
        }
        if a.json {
            let mut v: serde_json::Value = serde_json::from_slice(&line.bytes)?;
            if let Some(o) = v.as_object_mut() {
                o.remove("prev");
            }
            say!("{v}");
            continue;
        }
        let who = match (&r.user, &r.claimed) {
            (Some(u), Some(c)) => format!("{u} (claims {c})"),
            (Some(u), None) => u.clone(),
            (None, Some(c)) => format!("unvouched (claims {c})"),
            (None, None) if r.interface.is_some() => "unvouched".into(),
            (None, None) => "-".into(),
        };
        let via = r.interface.as_deref().unwrap_or("-");
        let kind = serde_json::to_value(r.kind)?;
        let kind = kind.as_str().unwrap_or("?");
        let what = summary(r);
        say!(
            "{:>6} {} {kind:<8} {via:<9} {who:<20} {what}",
            entry.seq,
            entry.ts
        );
    }
    Ok(())
}

/// One line about a record's data.
fn summary(r: &ihex_audit::Record) -> String {
    let d = &r.data;
    let s = |v: &serde_json::Value| {
        v.as_str()
            .map(str::to_owned)
            .unwrap_or_else(|| v.to_string())
    };
    match r.kind {
        ihex_audit::Kind::Command => d.get("command").map_or_else(|| d.to_string(), s),
        ihex_audit::Kind::Answer => {
            let p = &d["payload"];
            let mut out = format!(
                "{} {}",
                s(&d["event"]),
                p["request_id"].as_str().unwrap_or("")
            );
            if let Some(res) = p["result"].as_str() {
                out.push_str(&format!(": {res}"));
            }
            if let Some(why) = p["reason"].as_str() {
                out.push_str(&format!(" ({why})"));
            }
            out
        }
        ihex_audit::Kind::Gap => format!("{} records lost (the trail could not record)", d["lost"]),
        _ => d.to_string(),
    }
}
