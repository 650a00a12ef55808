"""The kernels layer: the models and controllers as C (``generate``), how kernels are named and
identified (``naming``), the generated library through ctypes (``library``), and one calling
convention for CasADi and C kernels (``bind``)."""
