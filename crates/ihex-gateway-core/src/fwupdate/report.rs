//! What an update publishes: `fw_progress` per node (throttled) and one `fw_report` at the end.

use serde::{Deserialize, Serialize};

use crate::event::HexId;

/// How one node's update ended.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NodeOutcome {
    /// The new image runs and confirmed itself.
    Updated,
    /// The node refused the image (see `reason`); it runs its image as before.
    Refused,
    /// The new image never confirmed itself and the bootloader put the old one back.
    Reverted,
    /// The node stopped answering (see `reason` for the step).
    Unreachable,
    /// The update was stopped before this node was done (see `reason`).
    Failed,
    /// A lease holds the node and the command did not carry its token: not updated (see `reason`).
    Skipped,
    /// The element lost its power in the middle of its update because the static element
    /// powering it restarted (`reason` names it), and did not finish after being retried: not a
    /// fault of the image. It runs its old image, or the new one unconfirmed until it reverts.
    LostPower,
}

impl NodeOutcome {
    /// Every outcome (for tallies that show each from the start, such as metrics).
    pub const ALL: [NodeOutcome; 7] = [
        NodeOutcome::Updated,
        NodeOutcome::Refused,
        NodeOutcome::Reverted,
        NodeOutcome::Unreachable,
        NodeOutcome::Failed,
        NodeOutcome::Skipped,
        NodeOutcome::LostPower,
    ];

    /// The word `fw_report` writes for it.
    pub fn as_str(self) -> &'static str {
        match self {
            NodeOutcome::Updated => "updated",
            NodeOutcome::Refused => "refused",
            NodeOutcome::Reverted => "reverted",
            NodeOutcome::Unreachable => "unreachable",
            NodeOutcome::Failed => "failed",
            NodeOutcome::Skipped => "skipped",
            NodeOutcome::LostPower => "lost_power",
        }
    }
}

/// Payload of `fw_progress`: where one node is.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct FwProgress {
    /// The `fw_update` command's `request_id`.
    pub request_id: Option<String>,
    /// The node.
    pub node: HexId,
    /// `begin`, a transfer phase the node reported (`header`, `erasing`, `receiving`,
    /// `complete`, `verifying`, `rebooting`), or `confirming` (the new image on trial).
    pub phase: String,
    /// Share of the image the node holds, 0–100: what it last said it has plus the frames sent
    /// to it since (a frame it lost shows at its next answer). Published at every 5 % step.
    pub percent: u8,
}

/// One node's line in `fw_report`.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct NodeReport {
    /// The node.
    pub node: HexId,
    /// How it ended.
    pub outcome: NodeOutcome,
    /// Why, for `refused` (the node's refusal name), `unreachable` and `failed`.
    pub reason: Option<String>,
    /// From the start of the update to this node's outcome, ms.
    pub duration_ms: u64,
}

/// Payload of `fw_report`: the end of an update.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct FwReport {
    /// The `fw_update` command's `request_id`.
    pub request_id: Option<String>,
    /// The image's ID (8 hex digits).
    pub image_id: String,
    /// The image's firmware version.
    pub version: String,
    /// The release notes the image carries (header format 2), `null` without.
    #[serde(default)]
    pub notes: Option<String>,
    /// From start to the last outcome, ms.
    pub duration_ms: u64,
    /// Data frames sent (every node, resends included).
    pub frames_sent: u64,
    /// Bus share the update was capped to, %.
    pub bus_share: u8,
    /// Per node, by ID.
    pub nodes: Vec<NodeReport>,
}

/// Payload of `fw_correction`: a node reported in with the new image confirmed after the update
/// had given it another outcome (during the update, before its report; or after it). The report
/// is not contradicted silently: this event says which line changed.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct FwCorrection {
    /// The `fw_update` command's `request_id`.
    pub request_id: Option<String>,
    /// The image's ID (8 hex digits).
    pub image_id: String,
    /// The image's firmware version.
    pub version: String,
    /// The node.
    pub node: HexId,
    /// The outcome it was given (`unreachable`, `lost_power`).
    pub was: NodeOutcome,
    /// Its outcome now (`updated`).
    pub outcome: NodeOutcome,
    /// What showed it.
    pub reason: String,
}

impl FwReport {
    /// True when every node ended `updated`.
    pub fn all_updated(&self) -> bool {
        self.nodes.iter().all(|n| n.outcome == NodeOutcome::Updated)
    }
}

#[cfg(test)]
mod tests {
    use super::NodeOutcome;

    #[test]
    fn every_outcome_is_listed_once_under_the_word_the_report_writes() {
        for (i, o) in NodeOutcome::ALL.into_iter().enumerate() {
            assert_eq!(
                serde_json::to_string(&o).unwrap(),
                format!("\"{}\"", o.as_str())
            );
            assert!(!NodeOutcome::ALL[..i].contains(&o), "{o:?} twice");
        }
    }
}
