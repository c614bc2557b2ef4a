//! Which role each RPC needs. Every method of the public services is
//! listed; anything else (a method added without a rule, a mistyped path)
//! needs `control`, so a new RPC cannot slip through as readable.

use crate::tokens::Role;

/// What a call to a gRPC path needs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// No token: health checks, for load balancers and probes.
    Open,
    /// A token whose role grants this one.
    Needs(Role),
}

/// The services anyone may call without a token.
const OPEN_SERVICES: &[&str] = &["grpc.health.v1.Health"];

/// The rules, by full method path.
pub const RULES: &[(&str, Role)] = &[
    ("/tweezer.v1.Learner/StreamSteps", Role::Actor),
    ("/tweezer.v1.Learner/GetSnapshot", Role::Read),
    ("/tweezer.v1.Learner/GetStatus", Role::Read),
    ("/tweezer.v1.Learner/ListSnapshots", Role::Read),
    ("/tweezer.v1.Learner/PauseLearning", Role::Control),
    ("/tweezer.v1.Learner/ResumeLearning", Role::Control),
    ("/tweezer.v1.Learner/Checkpoint", Role::Control),
    ("/tweezer.v1.HardwareAgent/GetStatus", Role::Read),
    ("/tweezer.v1.HardwareAgent/StreamTelemetry", Role::Read),
    ("/tweezer.v1.HardwareAgent/StartEpisode", Role::Control),
    ("/tweezer.v1.HardwareAgent/StopEpisode", Role::Control),
    ("/tweezer.v1.HardwareAgent/EmergencyStop", Role::Control),
    (
        "/tweezer.v1.HardwareAgent/ResetEmergencyStop",
        Role::Control,
    ),
    ("/tweezer.v1.HardwareAgent/LoadPolicy", Role::Control),
    ("/tweezer.v1.HardwareAgent/SetOverlay", Role::Control),
    (
        "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
        Role::Read,
    ),
];

/// What a call to `path` (`/package.Service/Method`) needs.
pub fn access(path: &str) -> Access {
    let service = path.trim_start_matches('/').split('/').next().unwrap_or("");
    if OPEN_SERVICES.contains(&service) {
        return Access::Open;
    }
    RULES
        .iter()
        .find(|(p, _)| *p == path)
        .map_or(Access::Needs(Role::Control), |(_, role)| {
            Access::Needs(*role)
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;
    use prost_types::FileDescriptorSet;

    #[test]
    fn every_method_of_the_public_services_has_a_rule() {
        let set = FileDescriptorSet::decode(tweezer_proto::FILE_DESCRIPTOR_SET).unwrap();
        let mut methods = Vec::new();
        for file in &set.file {
            for service in &file.service {
                for method in &service.method {
                    methods.push(format!(
                        "/{}.{}/{}",
                        file.package(),
                        service.name(),
                        method.name()
                    ));
                }
            }
        }
        assert_eq!(methods.len(), RULES.len() - 1, "{methods:?}");
        for method in &methods {
            assert!(
                RULES.iter().any(|(p, _)| p == method),
                "{method} has no rule"
            );
        }
    }

    #[test]
    fn health_is_open_and_unknown_paths_need_control() {
        assert_eq!(access("/grpc.health.v1.Health/Check"), Access::Open);
        assert_eq!(access("/grpc.health.v1.Health/Watch"), Access::Open);
        assert_eq!(
            access("/tweezer.v1.Learner/GetStatus"),
            Access::Needs(Role::Read)
        );
        assert_eq!(
            access("/tweezer.v1.Learner/DropEverything"),
            Access::Needs(Role::Control)
        );
        assert_eq!(access("/nonsense"), Access::Needs(Role::Control));
    }
}
