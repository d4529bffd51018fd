"""Generated gRPC stubs for proto/deepcontact/v1/warmstart.proto.

Do not edit: regenerate with `make proto` (python -m deepcontact.protogen).
tests/deepcontact/test_protogen.py fails when these are stale.
"""
