// The Linux MCU peer's GPIO shim (../shared/peers/linux/fakegpio.c, used
// as it is) with inputs a test can change while the MCU runs: every
// input read returns the first byte of the file FAKEGPIO_IN_FILE as a
// digit ('0' or '1'), or FAKEGPIO_IN's value as before if that variable
// is not set. An output line's level when it is requested (its default
// value, which the shim does not log) is logged too, as a write, so that
// a pin set up on or off shows in the log.
//
// ADC inputs: with FAKEIIO_DIR set, the MCU's IIO channel files
// (/sys/bus/iio/devices/iio:device0/in_voltageN_raw, which Klipper's
// Linux MCU opens once at config_analog_in and reads with pread at offset
// 0 for every sample) are that folder's in_voltageN_raw: a test writes
// the raw reading there (0..4095 as decimal text, rewritten in place).
//
// Build: cc -shared -fPIC -O2 -I <peers>/linux -o X.so inputs_from_file.c -ldl
#define _GNU_SOURCE
#include <dlfcn.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

// The shim finds the real open() and open64() through dlsym: its lookups
// go through fake_iio_dlsym, which hands it the IIO-redirecting ones.
static void *fake_iio_dlsym(void *handle, const char *symbol);
#define ioctl fakegpio_ioctl
#define dlsym fake_iio_dlsym
#include "fakegpio.c"
#undef dlsym
#undef ioctl

#define IIO_PREFIX "/sys/bus/iio/devices/iio:device0/"

// `path`, or its stand-in under FAKEIIO_DIR (in `buf`) for an IIO
// channel file.
static const char *iio_path(const char *path, char *buf, size_t len)
{
    const char *dir = getenv("FAKEIIO_DIR");
    size_t n = strlen(IIO_PREFIX);
    if (!dir || !path || strncmp(path, IIO_PREFIX, n) != 0)
        return path;
    if (snprintf(buf, len, "%s/%s", dir, path + n) >= (int)len)
        return path;
    return buf;
}

static int iio_open_with(const char *sym, const char *p, int flags, mode_t mode)
{
    char buf[512];
    int (*real)(const char *, int, ...) = dlsym(RTLD_NEXT, sym);
    return real(iio_path(p, buf, sizeof(buf)), flags, mode);
}

static int iio_open(const char *p, int flags, ...)
{
    va_list ap; va_start(ap, flags); mode_t m = va_arg(ap, int); va_end(ap);
    return iio_open_with("open", p, flags, m);
}

static int iio_open64(const char *p, int flags, ...)
{
    va_list ap; va_start(ap, flags); mode_t m = va_arg(ap, int); va_end(ap);
    return iio_open_with("open64", p, flags, m);
}

static void *fake_iio_dlsym(void *handle, const char *symbol)
{
    if (handle == RTLD_NEXT && strcmp(symbol, "open") == 0)
        return (void *)iio_open;
    if (handle == RTLD_NEXT && strcmp(symbol, "open64") == 0)
        return (void *)iio_open64;
    return dlsym(handle, symbol);
}

int openat(int dirfd, const char *p, int flags, ...)
{
    va_list ap; va_start(ap, flags); mode_t m = va_arg(ap, int); va_end(ap);
    char buf[512];
    int (*real)(int, const char *, int, ...) = dlsym(RTLD_NEXT, "openat");
    return real(dirfd, iio_path(p, buf, sizeof(buf)), flags, m);
}

// The input file, opened at the first read (-1: not yet; -2: none).
static int input_fd = -1;

int ioctl(int fd, unsigned long req, ...)
{
    va_list ap;
    va_start(ap, req);
    void *arg = va_arg(ap, void *);
    va_end(ap);
    if (req == GPIO_GET_LINEHANDLE_IOCTL && fd >= 0 && fd < MAXFD
        && fd_kind[fd] == 1) {
        struct gpiohandle_request *r = arg;
        int ret = fakegpio_ioctl(fd, req, arg);
        if (ret == 0 && (r->flags & GPIOHANDLE_REQUEST_OUTPUT)) {
            struct gpiohandle_data d = { .values = { r->default_values[0] } };
            fakegpio_ioctl(r->fd, GPIOHANDLE_SET_LINE_VALUES_IOCTL, &d);
        }
        return ret;
    }
    if (req == GPIOHANDLE_GET_LINE_VALUES_IOCTL && fd >= 0 && fd < MAXFD
        && fd_kind[fd] == 2) {
        if (input_fd == -1) {
            const char *path = getenv("FAKEGPIO_IN_FILE");
            input_fd = path ? open(path, O_RDONLY | O_CLOEXEC) : -2;
            if (input_fd < 0)
                input_fd = -2;
        }
        char level;
        if (input_fd >= 0 && pread(input_fd, &level, 1, 0) == 1) {
            struct gpiohandle_data *d = arg;
            d->values[0] = level == '1';
            return 0;
        }
    }
    return fakegpio_ioctl(fd, req, arg);
}
