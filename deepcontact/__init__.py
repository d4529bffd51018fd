"""deepcontact: warm-start Box2D's contact solver with a neural network served over gRPC.

Packages:
    deepcontact  the command line and what every part shares (grid spec, transfer)
    simclient    scenes, the patched-engine wrapper, warm-start providers, the client
    server       the gRPC warm-start service
    training     data sets, models, training, ONNX export
    bench        benchmarks
"""

__version__ = "0.1.0"
