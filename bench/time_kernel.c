/* Times one kernel of libcochlea.so in C, with no Python in the loop.
 *
 *   time_kernel LIBRARY KERNEL INPUTS REPETITIONS CALLS
 *
 * INPUTS is a binary file of doubles: the kernel's inputs, dense, one after the other. Prints
 * the median over REPETITIONS of the time per call (ns) of CALLS back-to-back calls. */
#define _POSIX_C_SOURCE 199309L
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

typedef long long casadi_int;
typedef int (*kernel_t)(const double**, double**, casadi_int*, double*, int);
typedef casadi_int (*count_t)(void);
typedef const casadi_int* (*sparsity_t)(casadi_int);

static double now_ns(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return 1e9 * (double)t.tv_sec + (double)t.tv_nsec;
}

static int compare(const void* a, const void* b) {
  double x = *(const double*)a, y = *(const double*)b;
  return (x > y) - (x < y);
}

static void* symbol(void* lib, const char* kernel, const char* suffix) {
  char name[512];
  snprintf(name, sizeof name, "%s%s", kernel, suffix);
  void* s = dlsym(lib, name);
  if (!s) { fprintf(stderr, "time_kernel: no symbol %s\n", name); exit(2); }
  return s;
}

static casadi_int numel(const casadi_int* sp) { return sp[0] * sp[1]; }

int main(int argc, char** argv) {
  if (argc != 6) { fprintf(stderr, "usage: time_kernel LIB KERNEL INPUTS REPS CALLS\n"); return 2; }
  void* lib = dlopen(argv[1], RTLD_NOW);
  if (!lib) { fprintf(stderr, "time_kernel: %s\n", dlerror()); return 2; }
  const char* kernel = argv[2];
  kernel_t f;
  count_t n_in, n_out;
  sparsity_t sp_in, sp_out;
  *(void**)&f = symbol(lib, kernel, "");
  *(void**)&n_in = symbol(lib, kernel, "_n_in");
  *(void**)&n_out = symbol(lib, kernel, "_n_out");
  *(void**)&sp_in = symbol(lib, kernel, "_sparsity_in");
  *(void**)&sp_out = symbol(lib, kernel, "_sparsity_out");
  casadi_int ni = n_in(), no = n_out(), total = 0, i;
  for (i = 0; i < ni; ++i) total += numel(sp_in(i));
  double* inputs = malloc((size_t)(total > 0 ? total : 1) * sizeof(double));
  FILE* file = fopen(argv[3], "rb");
  if (!file || fread(inputs, sizeof(double), (size_t)total, file) != (size_t)total) {
    fprintf(stderr, "time_kernel: cannot read %lld doubles from %s\n", total, argv[3]);
    return 2;
  }
  fclose(file);
  const double** arg = malloc((size_t)ni * sizeof(double*));
  double** res = malloc((size_t)no * sizeof(double*));
  for (i = 0, total = 0; i < ni; ++i) { arg[i] = inputs + total; total += numel(sp_in(i)); }
  for (i = 0; i < no; ++i) res[i] = malloc((size_t)(numel(sp_out(i)) + 1) * sizeof(double));
  long reps = atol(argv[4]), calls = atol(argv[5]), r, c;
  double* per_call = malloc((size_t)reps * sizeof(double));
  for (c = 0; c < calls; ++c) f(arg, res, 0, 0, 0);  /* warm up */
  for (r = 0; r < reps; ++r) {
    double start = now_ns();
    for (c = 0; c < calls; ++c) {
      if (f(arg, res, 0, 0, 0)) { fprintf(stderr, "time_kernel: %s failed\n", kernel); return 1; }
    }
    per_call[r] = (now_ns() - start) / (double)calls;
  }
  qsort(per_call, (size_t)reps, sizeof(double), compare);
  printf("%.3f\n", per_call[reps / 2]);
  return 0;
}
