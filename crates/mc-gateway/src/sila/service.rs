//! `SiLAService` (mandatory for every SiLA server): who the server is, which features it
//! implements and their definitions, and its name, which a client may change.

use std::{path::PathBuf, sync::Mutex};

use tonic::{Request, Response, Status};
use tracing::{info, warn};

use super::{
    defined_error,
    identity::{self, Identity},
    proto::{framework, sila_service as pb},
    validation_error, CANCEL_CONTROLLER, CANCEL_CONTROLLER_FDL, FIRMWARE_UPDATE,
    FIRMWARE_UPDATE_FDL, ISLAND_CONTROL, ISLAND_CONTROL_FDL, LOCK_CONTROLLER, LOCK_CONTROLLER_FDL,
    SILA_SERVICE, SILA_SERVICE_FDL,
};

/// The server type: what kind of device this is (`[A-Z][a-zA-Z0-9]*`).
pub const SERVER_TYPE: &str = "IhexIsland";

/// Every implemented feature with its definition.
pub const FEATURES: [(&str, &str); 5] = [
    (SILA_SERVICE, SILA_SERVICE_FDL),
    (ISLAND_CONTROL, ISLAND_CONTROL_FDL),
    (LOCK_CONTROLLER, LOCK_CONTROLLER_FDL),
    (FIRMWARE_UPDATE, FIRMWARE_UPDATE_FDL),
    (CANCEL_CONTROLLER, CANCEL_CONTROLLER_FDL),
];

/// The `SiLAService` feature.
pub struct Service {
    identity: Mutex<Identity>,
    file: Option<PathBuf>,
    description: String,
}

impl Service {
    /// The feature for `identity`, kept in `file` when the name changes.
    pub fn new(identity: Identity, file: Option<PathBuf>, description: String) -> Service {
        Service {
            identity: Mutex::new(identity),
            file,
            description,
        }
    }

    fn identity(&self) -> Identity {
        self.identity
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }
}

fn text(value: impl Into<String>) -> Option<framework::String> {
    Some(framework::String {
        value: value.into(),
    })
}

/// The definition of the feature `identifier` names: fully qualified, compared as SiLA says
/// identifiers compare (ignoring case).
pub fn definition(identifier: &str) -> Option<&'static str> {
    FEATURES
        .iter()
        .find(|(id, _)| id.eq_ignore_ascii_case(identifier))
        .map(|(_, fdl)| *fdl)
}

#[tonic::async_trait]
impl pb::si_la_service_server::SiLaService for Service {
    async fn get_feature_definition(
        &self,
        request: Request<pb::GetFeatureDefinitionParameters>,
    ) -> Result<Response<pb::GetFeatureDefinitionResponses>, Status> {
        let Some(id) = request.into_inner().feature_identifier else {
            return Err(validation_error(
                SILA_SERVICE,
                "GetFeatureDefinition",
                "FeatureIdentifier",
                "missing parameter FeatureIdentifier",
            ));
        };
        match definition(&id.value) {
            Some(fdl) => Ok(Response::new(pb::GetFeatureDefinitionResponses {
                feature_definition: text(fdl),
            })),
            None => Err(defined_error(
                SILA_SERVICE,
                "UnimplementedFeature",
                &format!(
                    "this server does not implement {:?}; it implements {}",
                    id.value,
                    FEATURES.map(|(id, _)| id).join(", ")
                ),
            )),
        }
    }

    async fn set_server_name(
        &self,
        request: Request<pb::SetServerNameParameters>,
    ) -> Result<Response<pb::SetServerNameResponses>, Status> {
        let invalid =
            |why: &str| validation_error(SILA_SERVICE, "SetServerName", "ServerName", why);
        let Some(name) = request.into_inner().server_name else {
            return Err(invalid("missing parameter ServerName"));
        };
        identity::check_name(&name.value).map_err(|why| invalid(&why))?;
        let changed = {
            let mut id = self.identity.lock().unwrap_or_else(|e| e.into_inner());
            id.name = name.value;
            id.clone()
        };
        if let Some(file) = &self.file {
            if let Err(e) = identity::save(file, &changed) {
                warn!(error = %e, "SiLA server name not kept for the next start");
            }
        }
        info!(name = %changed.name, "SiLA server renamed");
        Ok(Response::new(pb::SetServerNameResponses {}))
    }

    async fn get_server_name(
        &self,
        _: Request<pb::GetServerNameParameters>,
    ) -> Result<Response<pb::GetServerNameResponses>, Status> {
        Ok(Response::new(pb::GetServerNameResponses {
            server_name: text(self.identity().name),
        }))
    }

    async fn get_server_type(
        &self,
        _: Request<pb::GetServerTypeParameters>,
    ) -> Result<Response<pb::GetServerTypeResponses>, Status> {
        Ok(Response::new(pb::GetServerTypeResponses {
            server_type: text(SERVER_TYPE),
        }))
    }

    async fn get_server_uuid(
        &self,
        _: Request<pb::GetServerUuidParameters>,
    ) -> Result<Response<pb::GetServerUuidResponses>, Status> {
        Ok(Response::new(pb::GetServerUuidResponses {
            server_uuid: text(self.identity().uuid),
        }))
    }

    async fn get_server_description(
        &self,
        _: Request<pb::GetServerDescriptionParameters>,
    ) -> Result<Response<pb::GetServerDescriptionResponses>, Status> {
        Ok(Response::new(pb::GetServerDescriptionResponses {
            server_description: text(self.description.clone()),
        }))
    }

    async fn get_server_version(
        &self,
        _: Request<pb::GetServerVersionParameters>,
    ) -> Result<Response<pb::GetServerVersionResponses>, Status> {
        Ok(Response::new(pb::GetServerVersionResponses {
            server_version: text(env!("CARGO_PKG_VERSION")),
        }))
    }

    async fn get_server_vendor_url(
        &self,
        _: Request<pb::GetServerVendorUrlParameters>,
    ) -> Result<Response<pb::GetServerVendorUrlResponses>, Status> {
        Ok(Response::new(pb::GetServerVendorUrlResponses {
            server_vendor_url: text(env!("CARGO_PKG_REPOSITORY")),
        }))
    }

    async fn get_implemented_features(
        &self,
        _: Request<pb::GetImplementedFeaturesParameters>,
    ) -> Result<Response<pb::GetImplementedFeaturesResponses>, Status> {
        Ok(Response::new(pb::GetImplementedFeaturesResponses {
            implemented_features: FEATURES.iter().filter_map(|(id, _)| text(*id)).collect(),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn definitions_are_found_by_their_fully_qualified_identifier() {
        assert_eq!(definition(SILA_SERVICE), Some(SILA_SERVICE_FDL));
        assert_eq!(
            definition("de.ihex/bench/islandcontrol/v1"),
            Some(ISLAND_CONTROL_FDL)
        );
        assert_eq!(definition("de.ihex/bench/IslandControl/v2"), None);
        assert!(ISLAND_CONTROL_FDL.contains("<Identifier>IslandControl</Identifier>"));
    }
}
