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
// SPI: /dev/spidevB.D is a register chip (a MAX31865's or MAX31856's
// layout: the first byte of a transfer is the register address, bit 7
// set for a write; the chip answers a read with the registers from that
// address on). With FAKESPI_DIR set, the registers read are the bytes of
// that folder's file spidevB.D (at their address as offset; a test
// rewrites it in place); writes are logged as "<ns> spidevB.D <hex>". A
// write of the configuration register (0) with the fault-clear bit (0x02)
// clears the fault status register (7) in that file, as a MAX31865 does.
//
// Build: cc -shared -fPIC -O2 -I <peers>/linux -o X.so inputs_from_file.c -ldl
#define _GNU_SOURCE
#include <dlfcn.h>
#include <fcntl.h>
#include <stdio.h>
#include <linux/spi/spidev.h>
#include <stdint.h>
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
#define SPI_PREFIX "/dev/"
// Stand-in fd kinds (fakegpio's are 1 and 2).
#define KIND_PWM 3
#define KIND_SPI 4

// Each stand-in's name ("pwmchip0/pwm0/duty_cycle", "spidev0.0"), by fd.
static char fake_name[MAXFD][48];

// A stand-in for `path` if it is a PWM file or an SPI device, or -2.
static int fake_open(const char *path)
{
    const char *name;
    int kind;
    if (path && strncmp(path, PWM_PREFIX, strlen(PWM_PREFIX)) == 0) {
        name = path + strlen(PWM_PREFIX);
        kind = KIND_PWM;
    } else if (path && strncmp(path, SPI_PREFIX "spidev", strlen(SPI_PREFIX) + 6) == 0) {
        name = path + strlen(SPI_PREFIX);
        kind = KIND_SPI;
    } else {
        return -2;
    }
    int fd = new_fd(kind, 0, 0);
    if (fd >= 0 && fd < MAXFD)
        snprintf(fake_name[fd], sizeof(fake_name[fd]), "%s", name);
    return fd;
}

// Logs "<ns> <stand-in's name> <text>" to FAKEGPIO_LOG.
static void fake_log(int fd, const char *text)
{
    if (!logf && getenv("FAKEGPIO_LOG"))
        logf = fopen(getenv("FAKEGPIO_LOG"), "a");
    if (logf) {
        struct timespec ts;
        clock_gettime(CLOCK_MONOTONIC, &ts);
        fprintf(logf, "%lld %s %s\n",
                (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec,
                fake_name[fd], text);
        fflush(logf);
    }
}

// The register file of SPI stand-in `fd` under FAKESPI_DIR, opened with
// `flags` (-1 if there is none).
static int spi_regs_open(int fd, int flags)
{
    const char *dir = getenv("FAKESPI_DIR");
    char path[512];
    if (!dir || snprintf(path, sizeof(path), "%s/%s", dir, fake_name[fd]) >= (int)sizeof(path))
        return -1;
    int (*real_open)(const char *, int, ...) = dlsym(RTLD_NEXT, "open");
    return real_open(path, flags | O_CLOEXEC);
}

// A register write to SPI stand-in `fd`: logged in hex; the fault-clear
// bit of the configuration register clears the fault status.
static void spi_write(int fd, const uint8_t *data, size_t len)
{
    char hex[2 * 64 + 1] = "";
    for (size_t i = 0; i < len && i < 64; i++)
        snprintf(hex + 2 * i, 3, "%02x", data[i]);
    fake_log(fd, hex);
    if (len >= 2 && data[0] == 0x80 && (data[1] & 0x02)) {
        int regs_fd = spi_regs_open(fd, O_WRONLY);
        uint8_t clear = 0;
        if (regs_fd >= 0) {
            if (pwrite(regs_fd, &clear, 1, 7) < 0)
                perror("fakespi fault clear");
            close(regs_fd);
        }
    }
}

ssize_t write(int fd, const void *buf, size_t len)
{
    static ssize_t (*real)(int, const void *, size_t);
    if (fd >= 0 && fd < MAXFD && fd_kind[fd] == KIND_PWM) {
        // Decimal text, maybe NUL-terminated.
        char value[32];
        size_t n = len < sizeof(value) - 1 ? len : sizeof(value) - 1;
        memcpy(value, buf, n);
        value[n] = 0;
        value[strcspn(value, "\n")] = 0;
        fake_log(fd, value);
        return len;
    }
    if (fd >= 0 && fd < MAXFD && fd_kind[fd] == KIND_SPI) {
        spi_write(fd, buf, len);
        return len;
    }
    if (!real)
        real = dlsym(RTLD_NEXT, "write");
    return real(fd, buf, len);
}

// One SPI_IOC_MESSAGE transfer on stand-in `fd`: a register write is
// logged, a read answered from FAKESPI_DIR's register file.
static void spi_transfer(int fd, struct spi_ioc_transfer *t)
{
    uint8_t *tx = (uint8_t *)(uintptr_t)t->tx_buf;
    uint8_t *rx = (uint8_t *)(uintptr_t)t->rx_buf;
    uint32_t len = t->len;
    if (!len || !tx || !rx)
        return;
    if (tx[0] & 0x80) {
        spi_write(fd, tx, len);
        memset(rx, 0, len);
        return;
    }
    uint8_t regs[128] = { 0 };
    int regs_fd = spi_regs_open(fd, O_RDONLY);
    if (regs_fd >= 0) {
        if (pread(regs_fd, regs, sizeof(regs), 0) < 0)
            memset(regs, 0, sizeof(regs));
        close(regs_fd);
    }
    uint8_t addr = tx[0] & 0x7f;
    rx[0] = 0;
    for (uint32_t i = 1; i < len; i++)
        rx[i] = regs[(addr + i - 1) & 0x7f];
}

static int iio_open_with(const char *sym, const char *p, int flags, mode_t mode)
{
    int fake = fake_open(p);
    if (fake != -2)
        return fake;
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
    if (fd >= 0 && fd < MAXFD && fd_kind[fd] == KIND_SPI) {
        // Mode and speed are taken; a transfer is answered.
        if (req == SPI_IOC_MESSAGE(1))
            spi_transfer(fd, arg);
        return 0;
    }
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
