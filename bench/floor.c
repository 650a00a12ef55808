/* The benchmark's floor: a kernel with CasADi's calling convention that does nothing. Called
 * through ctypes exactly like a generated step, it measures the cost of the call alone. */
int cochlea_floor(const double** arg, double** res, long long* iw, double* w, int mem) {
  (void)arg; (void)res; (void)iw; (void)w; (void)mem;
  return 0;
}
