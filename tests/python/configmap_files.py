"""Writes each key of every ConfigMap in a rendered manifest to a file.

Usage: configmap_files.py RENDERED.yaml OUT_DIR
"""

import os
import sys

import yaml


def main(rendered, out):
    with open(rendered) as f:
        for document in yaml.safe_load_all(f):
            if document and document.get("kind") == "ConfigMap":
                for name, text in document.get("data", {}).items():
                    with open(os.path.join(out, name), "w") as g:
                        g.write(text)
                    print(name)


if __name__ == "__main__":
    main(*sys.argv[1:])
