"""The lab: research instruments beside the product (lab/README.md).

Importing lab registers its warm starts with the product's registry (simclient.warmstarts):
oracle:VARIANT (lab.oracles), the probes such as solve@K and jitter@S (lab.probes) and the
composites such as pick:W1+W2+... and price:W1+W2+... (lab.composites). Its commands are the
`deepcontact lab` group (lab.commands). The lab builds on the product; nothing in the product
imports it.
"""

from lab import composites, oracles, probes  # noqa: F401  (each registers its warm starts)
