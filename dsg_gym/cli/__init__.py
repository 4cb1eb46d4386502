"""Console scripts of the runtime, one module each (argparse + ``main`` only; the work is in the library):
``dsg-demo`` (:mod:`.demo`), ``dsg-collect`` (:mod:`.collect`), ``dsg-export`` (:mod:`.export`)."""
