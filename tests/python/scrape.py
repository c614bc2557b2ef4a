"""Scrapes a Prometheus endpoint over TLS, with and without a bearer token,
and parses the metrics with the reference OpenMetrics parser. Prints one
JSON object: the status without the token, and each family's type and
unlabelled samples.

Usage: scrape.py ADDR CA_FILE TOKEN_FILE
"""

import json
import ssl
import sys
import urllib.error
import urllib.request

from prometheus_client.openmetrics.parser import text_string_to_metric_families


def main(address, ca_file, token_file):
    with open(token_file) as f:
        token = f.read().strip()
    context = ssl.create_default_context(cafile=ca_file)
    url = f"https://{address}/metrics"
    try:
        urllib.request.urlopen(url, context=context, timeout=10)
        without_token = 200
    except urllib.error.HTTPError as e:
        without_token = e.code
    request = urllib.request.Request(
        url,
        headers={
            "Authorization": f"Bearer {token}",
            "Accept": "application/openmetrics-text; version=1.0.0",
        },
    )
    with urllib.request.urlopen(request, context=context, timeout=10) as response:
        text = response.read().decode()
    families = {
        family.name: {
            "type": family.type,
            "samples": {s.name: s.value for s in family.samples if not s.labels},
        }
        for family in text_string_to_metric_families(text)
    }
    print(json.dumps({"without_token": without_token, "families": families}))


if __name__ == "__main__":
    main(*sys.argv[1:])
