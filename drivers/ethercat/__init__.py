"""The ``ethercat://`` drive: an EtherCAT master for CiA 402 (CoE) drives, on pysoem."""
