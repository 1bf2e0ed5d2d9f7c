"""I/O with the Stäubli controller: one link interface, one module per protocol.

May import only the standard library, pymodbus and pyserial (design.md §2).  The DICOM client is
:mod:`dicomnet.scu`.
"""
