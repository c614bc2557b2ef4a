"""A foreign client of the learner: stubs generated from proto/ by
grpcio-tools, the real grpcio client over TLS with a bearer token, the
standard health service, and the Prometheus endpoint parsed by the
reference OpenMetrics parser. Prints one JSON object of what it saw.

Usage: learner_client.py STUBS_DIR GRPC_ADDR METRICS_ADDR CA_FILE TOKEN_FILE
"""

import json
import ssl
import sys
import urllib.request


def main(stubs, address, metrics_address, ca_file, token_file):
    sys.path.insert(0, stubs)
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc
    from prometheus_client.openmetrics.parser import text_string_to_metric_families
    from tweezer.v1 import learner_pb2, learner_pb2_grpc

    with open(ca_file, "rb") as f:
        ca = f.read()
    with open(token_file) as f:
        token = f.read().strip()
    credentials = grpc.ssl_channel_credentials(root_certificates=ca)
    with grpc.secure_channel(address, credentials) as channel:
        learner = learner_pb2_grpc.LearnerStub(channel)
        status = learner.GetStatus(
            learner_pb2.LearnerStatusRequest(),
            metadata=[("authorization", f"Bearer {token}")],
            timeout=10,
        )
        try:
            learner.GetStatus(learner_pb2.LearnerStatusRequest(), timeout=10)
            without_token = "OK"
        except grpc.RpcError as e:
            without_token = e.code().name
        health = health_pb2_grpc.HealthStub(channel).Check(
            health_pb2.HealthCheckRequest(service="tweezer.v1.Learner"), timeout=10
        )

    context = ssl.create_default_context(cafile=ca_file)
    def scrape(accept):
        headers = {"Authorization": f"Bearer {token}"}
        if accept:
            headers["Accept"] = accept
        request = urllib.request.Request(f"https://{metrics_address}/metrics", headers=headers)
        with urllib.request.urlopen(request, context=context, timeout=10) as response:
            return response.headers["Content-Type"], response.read().decode()

    content_type, text = scrape("application/openmetrics-text; version=1.0.0")
    # Without asking: Prometheus' text format 0.0.4, read by its own parser.
    from prometheus_client.parser import text_string_to_metric_families as text_families

    plain_type, plain = scrape(None)
    plain_families = {f.name: f.type for f in text_families(plain)}
    families = {}
    for family in text_string_to_metric_families(text):
        families[family.name] = {
            "type": family.type,
            "samples": {s.name: s.value for s in family.samples if not s.labels},
        }

    print(
        json.dumps(
            {
                "buffer_capacity": status.buffer_capacity,
                "latest_snapshot": status.latest_snapshot,
                "limiter_state": status.limiter_state,
                "without_token": without_token,
                "health": health_pb2.HealthCheckResponse.ServingStatus.Name(health.status),
                "content_type": content_type,
                "plain_content_type": plain_type,
                "plain_families": plain_families,
                "families": families,
            }
        )
    )


if __name__ == "__main__":
    main(*sys.argv[1:])
