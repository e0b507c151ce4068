import sys

from shared.blas import single_threaded_blas

single_threaded_blas()  # before numpy loads BLAS (OPENBLAS_NUM_THREADS etc. set by the user win)

from cloud.daemon.node import main  # noqa: E402

sys.exit(main())
