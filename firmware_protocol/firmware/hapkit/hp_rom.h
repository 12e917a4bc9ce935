/*
 * hp_rom.h -- force-included (-include) in the Hapkit builds: the C codec's constant
 * tables go to flash (avr-libc PROGMEM, read with lpm), not to the 2 KiB of RAM.
 */
#ifndef HK_HP_ROM_H
#define HK_HP_ROM_H
#include <avr/pgmspace.h>
#define HP_ROM PROGMEM
#define HP_ROM_U16(p) pgm_read_word(p)
#endif
