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
// Hardware PWM: Klipper's Linux MCU sets a channel up by writing the
// files period, duty_cycle and enable of /sys/class/pwm/pwmchipC/pwmN/
// (keeping duty_cycle open for its updates, written with write() at the
// file's position). Here those files are stand-ins that log each write to
// FAKEGPIO_LOG as "<monotonic ns> pwmchipC/pwmN/FILE <value>".
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

#define PWM_PREFIX "/sys/class/pwm/"

// Each hardware PWM stand-in's name ("pwmchip0/pwm0/duty_cycle"), by fd.
static char pwm_file[MAXFD][48];

// A stand-in for the PWM file `path` (fd kind 3), or -2 if `path` is
// not one.
static int pwm_open(const char *path)
{
    size_t n = strlen(PWM_PREFIX);
    if (!path || strncmp(path, PWM_PREFIX, n) != 0)
        return -2;
    int fd = new_fd(3, 0, 0);
    if (fd >= 0 && fd < MAXFD)
        snprintf(pwm_file[fd], sizeof(pwm_file[fd]), "%s", path + n);
    return fd;
}

// Logs the value (decimal text, maybe NUL-terminated) written to the PWM
// stand-in `fd`.
static void pwm_log(int fd, const void *buf, size_t len)
{
    char value[32];
    size_t n = len < sizeof(value) - 1 ? len : sizeof(value) - 1;
    memcpy(value, buf, n);
    value[n] = 0;
    value[strcspn(value, "\n")] = 0;
    if (!logf && getenv("FAKEGPIO_LOG"))
        logf = fopen(getenv("FAKEGPIO_LOG"), "a");
    if (logf) {
        struct timespec ts;
        clock_gettime(CLOCK_MONOTONIC, &ts);
        fprintf(logf, "%lld %s %s\n",
                (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec,
                pwm_file[fd], value);
        fflush(logf);
    }
}

ssize_t write(int fd, const void *buf, size_t len)
{
    static ssize_t (*real)(int, const void *, size_t);
    if (fd >= 0 && fd < MAXFD && fd_kind[fd] == 3) {
        pwm_log(fd, buf, len);
        return len;
    }
    if (!real)
        real = dlsym(RTLD_NEXT, "write");
    return real(fd, buf, len);
}

static int iio_open_with(const char *sym, const char *p, int flags, mode_t mode)
{
    int pwm = pwm_open(p);
    if (pwm != -2)
        return pwm;
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
